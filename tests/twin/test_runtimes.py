"""The fast runtime and the asyncio runtime drive the same core: same scenario and seed, same journal."""

import sqlite3
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tests.conftest import qd_lab
from twin.device.driver import StepResult
from twin.core.errors import DriverError
from twin.runtime.lab import run
from twin.campaign.journal_read import read_events
from twin.scenario import parse

ROOT = Path(__file__).resolve().parents[2]
SHIPPED_VIRTUAL = ["flaky_lab", "quantum_dots", "catalyst", "bandgap", "jobshop"]  # mqtt_lab keeps wall time


def journal(db):
    with sqlite3.connect(db) as c:
        return (c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
                c.execute("SELECT * FROM experiments ORDER BY id").fetchall())


def lab_facts(summary):
    return {k: v for k, v in summary.to_dict().items() if k not in ("wall_s", "journal", "decision_ms")}


@pytest.mark.parametrize("name, seed", [(n, 5) for n in SHIPPED_VIRTUAL] + [("flaky_lab", 11)])
def test_both_runtimes_write_the_same_journal(tmp_path, name, seed):
    scenario = ROOT / "scenarios" / f"{name}.yaml"
    fast = run(scenario, journal=tmp_path / "fast.db", seed=seed, bus="memory", runtime="fast")
    slow = run(scenario, journal=tmp_path / "asyncio.db", seed=seed, bus="memory", runtime="asyncio")
    events_fast, exps_fast = journal(tmp_path / "fast.db")
    events_slow, exps_slow = journal(tmp_path / "asyncio.db")
    assert len(events_fast) > 100
    assert events_fast == events_slow
    assert exps_fast == exps_slow
    assert lab_facts(fast) == lab_facts(slow)


def test_the_flaky_lab_comparison_exercises_crashes_hangs_and_failures(tmp_path):
    s = run(ROOT / "scenarios" / "flaky_lab.yaml", journal=tmp_path / "j.db", seed=11, bus="memory", runtime="fast")
    assert s.steps_lost > 0 and s.timed_out > 0 and s.failed_attempts > s.timed_out + s.steps_lost
    # every time a device left the bus is a loss, as the journal has it; a device that crashed idle lost no step
    assert s.devices_lost == len(read_events(tmp_path / "j.db", "device.lost")) > s.steps_lost


class WaitsOnAsyncio:
    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        import asyncio

        await asyncio.sleep(1)
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        pass


def test_a_driver_that_awaits_asyncio_is_refused_by_the_fast_runtime_by_name(tmp_path):
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_runtimes:WaitsOnAsyncio",
                          "campaign.budget": 2}))
    with pytest.raises(DriverError, match=r"spectrometer-\d: the spectrometer driver awaited .* --runtime asyncio"):
        run(lab, journal=tmp_path / "j.db", runtime="fast")
    summary = run(lab, journal=tmp_path / "k.db")  # auto: falls back to the asyncio runtime, which runs it
    assert summary.done == 2


def test_the_fast_runtime_refuses_what_only_a_bus_can_do(tmp_path):
    from twin.core.errors import ClockError

    with pytest.raises(ClockError, match="the clock is scaled"):
        run(parse(qd_lab(clock={"mode": "scaled", "speed": 1e6})), journal=tmp_path / "j.db", runtime="fast")


@example(seed=14, budget=10, instances=2, restart_s=0.0)  # a cancel answered in the instant of a planner's answer
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10**6), budget=st.integers(1, 25), instances=st.integers(1, 3),
       restart_s=st.sampled_from([0.0, 600.0]))
def test_the_runtimes_agree_on_any_seed_and_lab_shape(tmp_path_factory, seed, budget, instances, restart_s):
    tmp = tmp_path_factory.mktemp("eq")
    over = {"campaign.budget": budget, "devices.reactor.instances": instances,
            "devices.spectrometer.faults.restart_s": restart_s}
    scenario = ROOT / "scenarios" / "flaky_lab.yaml"
    run(scenario, journal=tmp / "fast.db", seed=seed, bus="memory", runtime="fast", overrides=over)
    run(scenario, journal=tmp / "asyncio.db", seed=seed, bus="memory", runtime="asyncio", overrides=over)
    assert journal(tmp / "fast.db") == journal(tmp / "asyncio.db")


class NumpyOutputs:
    """A driver that returns numpy numbers and arrays, as real drivers do."""

    capabilities = frozenset({"measure"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        import numpy as np

        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({"peak_nm": np.float64(600.0) + ctx.rng.normal(), "count": np.int64(3),
                           "trace": np.linspace(0.0, 1.0, 5)}, sample)

    async def safe_state(self):
        pass


def test_numpy_outputs_travel_and_both_runtimes_agree(tmp_path):
    lab = parse(qd_lab(**{"devices.spectrometer.driver": "tests.twin.test_runtimes:NumpyOutputs",
                          "campaign.budget": 3}))
    fast = run(lab, journal=tmp_path / "fast.db", runtime="fast")
    slow = run(lab, journal=tmp_path / "asyncio.db", runtime="asyncio")
    assert fast.done == slow.done == 3
    assert journal(tmp_path / "fast.db") == journal(tmp_path / "asyncio.db")


def test_an_rl_agent_asked_in_process_decides_as_it_does_over_the_bus(tmp_path):
    """What benches and what-if do: the agent in the campaign's process lets the fast runtime run it."""
    from twin.core.errors import ClockError

    policy = {"campaign.scheduler": "rl:agents/policies/flaky_scheduler.zip", "campaign.budget": 30}
    scenario = ROOT / "scenarios" / "flaky_lab.yaml"
    with pytest.raises(ClockError, match="agent on the bus"):
        run(scenario, journal=tmp_path / "refused.db", seed=3, bus="memory", runtime="fast", overrides=policy)
    bus = run(scenario, journal=tmp_path / "bus.db", seed=3, bus="memory", overrides=policy)
    here = run(scenario, journal=tmp_path / "here.db", seed=3, bus="memory", runtime="fast", overrides=policy,
               agent_in_process=True)
    assert here.decisions > 20 and lab_facts(here) == lab_facts(bus)
    assert journal(tmp_path / "here.db")[1] == journal(tmp_path / "bus.db")[1]  # every experiment, as it ended


class MeasuresAfterIo:
    """The shipped spectrometer behind a call in a thread (a vendor's SDK): only the asyncio runtime can serve it."""

    def __init__(self, setup):
        from devices.spectrometer import Spectrometer

        self.inner = Spectrometer(setup)
        self.capabilities, self.outputs = self.inner.capabilities, self.inner.outputs

    async def run(self, step, params, sample, ctx):
        import asyncio

        await asyncio.to_thread(lambda: None)
        return await self.inner.run(step, params, sample, ctx)

    async def safe_state(self):
        pass


def test_a_lab_of_several_campaigns_runs_a_driver_the_fast_runtime_cannot_on_the_asyncio_one(tmp_path, caplog):
    """A lab file with campaigns ran only on the fast runtime in virtual time: such a driver stopped it, with advice
    (--runtime asyncio) that changed nothing. Now auto runs it again on the asyncio runtime from the start, as a
    single campaign does, and --runtime asyncio runs it there at once: the same journals as a lab of drivers that
    keep to the lab clock."""
    from tests.twin.shared_labs import LAB, SMALL, journal_tables
    from twin.runtime.lab import prepare
    from twin.runtime.shared_run import run_shared

    plain = prepare(LAB, seed=3, overrides=SMALL)
    sdk = prepare(LAB, seed=3, overrides={**SMALL, "devices.spectrometer.driver":
                                          "tests.twin.test_runtimes:MeasuresAfterIo"})
    expected = run_shared(plain, tmp_path / "plain", handle_signals=False)
    with pytest.raises(DriverError, match=r"spectrometer: the spectrometer driver awaited .* --runtime asyncio"):
        run_shared(sdk, tmp_path / "fast", handle_signals=False, runtime="fast")
    with caplog.at_level("WARNING", logger="twin.runtime.fallback"):
        auto = run_shared(sdk, tmp_path / "auto", handle_signals=False)
    said = [r.getMessage() for r in caplog.records if r.name == "twin.runtime.fallback"]
    assert len(said) == 1 and "running the lab again, from the start, on the asyncio runtime" in said[0]
    direct = run_shared(sdk, tmp_path / "asyncio", handle_signals=False, runtime="asyncio")
    tables = journal_tables(tmp_path / "plain")
    assert sum(c.done for c in expected.campaigns.values()) == 10
    for out, where in ((auto, "auto"), (direct, "asyncio")):
        assert out.lab_hours == expected.lab_hours
        assert {n: c.done for n, c in out.campaigns.items()} == {n: c.done for n, c in expected.campaigns.items()}
        assert journal_tables(tmp_path / where) == tables


def test_a_lab_run_again_on_the_asyncio_runtime_is_recorded_from_its_start_once(tmp_path, caplog):
    """`twin run LAB.yaml --save`: the recording of the first try (on the fast runtime, up to the driver that
    stopped it) is replaced by the lab's run from the start, so it equals the replay of the journals."""
    import subprocess
    import sys

    from tests.conftest import twin_cli
    from tests.twin.shared_labs import LAB, SMALL

    overrides = [a for k, v in SMALL.items() for a in ("--set", f"{k}={v}")]
    with caplog.at_level("WARNING", logger="twin.runtime.fallback"):
        res = twin_cli("run", LAB, *overrides, "--set",
                       "devices.spectrometer.driver=tests.twin.test_runtimes:MeasuresAfterIo", "--bus", "memory",
                       "--journal", tmp_path / "lab", "--save", tmp_path / "live.rrd")
    assert res.exit_code == 0, res.output
    assert "running the lab again, from the start, on the asyncio runtime" in caplog.text
    assert twin_cli("replay", tmp_path / "lab", "--save", tmp_path / "replay.rrd").exit_code == 0
    same = subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "compare", "--unordered",
                           str(tmp_path / "live.rrd"), str(tmp_path / "replay.rrd")], capture_output=True, text=True,
                          timeout=120)
    assert same.returncode == 0, same.stdout[-2000:] + same.stderr[-2000:]
