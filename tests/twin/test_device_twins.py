"""A twin for a driver (`devices.<type>.twin`): a lab with a real instrument, or with a driver that waits on I/O,
is still simulated where the clock is virtual — `twin whatif`, `twin bench`, `twin train`, `twin run --clock
virtual` — with the type's own timing and faults; without one, each of those says what to give."""

import asyncio
import json
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab, twin_cli
from twin.core.errors import ScenarioError
from twin.device.driver import StepResult
from twin.runtime.checks import checked
from twin.runtime.lab import run
from twin.scenario import parse

ROOT = Path(__file__).resolve().parents[2]
MQTT_LAB = str(ROOT / "scenarios" / "mqtt_lab.yaml")


class Sdk:
    """A measuring driver that calls a blocking vendor SDK in a thread, as docs/drivers.md advises."""

    capabilities = frozenset({"measure"})
    outputs = frozenset({"peak_nm"})

    def __init__(self, setup):
        pass

    async def run(self, step, params, sample, ctx):
        await asyncio.to_thread(time.sleep, 0.001)
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({"peak_nm": sample["peak_nm"]}, sample)

    async def safe_state(self):
        pass


def sdk_lab(twin: dict | None = None) -> dict:
    lab = qd_lab(**{
        "devices.reader": {"driver": "tests.twin.test_device_twins:Sdk", "steps": ["measure"],
                           "duration": {"mean_s": 300, "cv": 0.1}, **({"twin": twin} if twin else {})},
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "reader"}],
        "campaign.budget": 6, "campaign.planner": "random",
    })
    del lab["devices"]["spectrometer"]  # the reader measures: a spectrometer beside it would stay idle
    return lab


def invoke(*args: str):
    res = twin_cli(*args)
    return res.exit_code, res.stdout, " ".join(res.output.split())


def test_a_lab_with_an_mqtt_instrument_is_simulated_by_its_twin_without_a_broker(tmp_path):
    code, out, _ = invoke("whatif", MQTT_LAB, "--vary", "devices.synthesiser.instances=1,2", "--seeds", "2",
                          "--json")
    assert code == 0, out
    rows = {r["variant"]: r for r in json.loads(out)["variants"]}
    one, two = rows["devices.synthesiser.instances=1"], rows["as written"]
    assert 0 < two["lab_hours"][1] < one["lab_hours"][1]  # the target met, and sooner with two synthesisers
    summary = run(MQTT_LAB, clock="virtual", journal=tmp_path / "v.db")
    assert summary.done > 0 and summary.best and summary.utilisation["reader"] > 0
    code, _, said = invoke("run", MQTT_LAB, "--clock", "virtual", "--budget", "2", "--journal", str(tmp_path / "w.db"))
    assert code == 0 and "twins stand in: reader by spectrometer" in said


def test_without_a_twin_a_virtual_clock_says_which_field_to_give_in_one_line():
    code, _, said = invoke("whatif", MQTT_LAB, "--set", "devices.reader.twin=null", "--vary",
                           "devices.synthesiser.instances=1,2", "--seeds", "1")
    assert code == 2 and "Traceback" not in said
    assert "reader talks to a real instrument, which keeps wall time" in said
    assert "devices.reader.twin: {driver: NAME}" in said


def test_training_on_a_driver_that_waits_on_io_names_the_twin_to_give_and_trains_with_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(sdk_lab()))
    code, _, said = invoke("train", "lab.yaml", "--steps", "600", "--eval-every", "300", "--out", "p.zip")
    assert code == 2 and "awaited an asyncio future" in said
    assert "`twin train` runs every episode on the fast runtime" in said and "devices.reader.twin:" in said
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(sdk_lab({"driver": "spectrometer"})))
    code, _, said = invoke("train", "lab.yaml", "--steps", "600", "--eval-every", "300", "--out", "p.zip")
    assert code == 0, said
    assert (tmp_path / "p.zip").exists()
    # its own driver, at 4,000× (at 20,000× a busy machine's lag timed steps out and quarantined a synthesiser)
    own = run(tmp_path / "lab.yaml", clock="scaled", speed=4000, journal=tmp_path / "own.db")
    assert own.done == 6


@pytest.mark.parametrize("twin, says", [
    ({"driver": "mqtt", "options": {"broker": "127.0.0.1:1", "topic": "t", "steps": ["measure"]}},
     "devices.reader.twin.driver: 'mqtt' talks to an instrument of its own"),
    ({"driver": "synthesiser"}, "devices.reader.twin.driver: 'synthesiser' runs ['prepare', 'react', 'synthesise'], "
                                "but the scenario asks it for ['measure']"),
    ({"driver": "spectrometer", "options": {"noise": 1}}, "devices.reader.twin.options.noise: the 'spectrometer' "
                                                           "driver takes no option 'noise'"),
    ({"driver": "machine", "options": {"steps": "measure"}}, "options.steps must be a list of step names"),
    ({"driver": "nope"}, "nope"),
])
def test_a_twin_that_cannot_stand_in_is_refused_naming_its_field(twin, says):
    with pytest.raises(ScenarioError) as exc:
        checked(parse(sdk_lab(twin)), "lab.yaml")
    assert says in str(exc.value)


def test_a_twin_that_only_keeps_time_serves_a_schedulers_training_and_says_what_it_cannot(tmp_path, caplog):
    lab = parse(sdk_lab({"driver": "machine", "options": {"steps": ["measure"]}}))
    checked(lab, "lab.yaml")  # a warning, not an error
    assert any("no device of the workflow with their twins (devices.*.twin) produces 'peak_nm'" in r.getMessage()
               for r in caplog.records)
    summary = run(lab, journal=tmp_path / "j.db")
    assert summary.done == 6 and not summary.targets_met_h  # every step run for its time; no output to score
    caplog.clear()
    checked(parse({**sdk_lab({"driver": "machine", "options": {"steps": ["measure"]}}),
                   "clock": {"mode": "scaled", "speed": 100}}), "lab.yaml")
    assert not caplog.records  # on a scaled clock the lab's own drivers run: nothing to warn of
    assert summary.utilisation["reader"] > 0


def test_people_take_no_twin():
    with pytest.raises(ScenarioError, match="a twin stands in for a driver, and people .driver: operator. are not one"):
        parse(qd_lab(**{"devices.spectrometer.driver": "operator", "devices.spectrometer.twin": {"driver": "machine"}}))


def test_a_driver_that_runs_the_steps_its_options_list_runs_the_types_steps_unless_they_list_others():
    """A machine ran only "op" unless its options listed the steps its device type had just been given."""
    from twin.runtime.assembly import load_driver

    washer = {"driver": "machine", "steps": ["wash", "rinse"], "duration": {"mean_s": 60, "cv": 0}}
    lab = parse(qd_lab(**{"devices.washer": washer}))
    assert load_driver(lab, "washer", "washer-1").capabilities == {"wash", "rinse"}
    lab = parse(qd_lab(**{"devices.washer": {**washer, "options": {"steps": ["wash"]}}}))
    with pytest.raises(ScenarioError, match=r"'machine' runs \['wash'\], but the scenario asks it for \['rinse'\]"):
        checked(lab, "lab.yaml")


def test_the_planners_workcell_is_simulated_whatever_the_scenarios_clock():
    """`twin train scenarios/mqtt_lab.yaml --agent planner` tried the MQTT broker ('reader-workcell: not connected'):
    the workcell loaded the lab's own drivers on the scenario's scaled clock."""
    from twin import open_workcell
    from twin.core.errors import DriverError
    from twin.runtime.assembly import prepare

    cell = open_workcell(prepare(MQTT_LAB))
    assert type(cell.drivers["reader"]).__name__ == "Spectrometer"
    with pytest.raises(DriverError, match=r"devices.reader: its driver talks to an instrument, which a workcell "
                                          r"\(simulated\) cannot: give devices.reader.twin"):
        open_workcell(prepare(MQTT_LAB, overrides={"devices.reader.twin": None}))


@pytest.mark.parametrize("driver", ["labtwin_acme_absent:Reader", "acme-reader"])
def test_a_driver_not_installed_here_is_said_where_its_twin_stands_in_and_refused_where_it_runs(tmp_path, caplog,
                                                                                                 driver):
    """A laptop without the instrument's package (its vendor's SDK) could not ask `twin whatif` of the lab: the lab's
    own driver was loaded to check it, though on a virtual clock its twin runs every one of its steps."""
    raw = {**sdk_lab({"driver": "spectrometer"}), "clock": {"mode": "scaled", "speed": 100}}
    raw["devices"]["reader"]["driver"] = driver
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    with pytest.raises(ScenarioError, match="devices.reader.driver: .*(labtwin_acme_absent|acme-reader)"):
        checked(parse(raw), "lab.yaml")  # on its own clock the lab runs its own driver
    checked(parse(raw), "lab.yaml", virtual=True)
    said = [r.getMessage() for r in caplog.records if "devices.reader.driver" in r.getMessage()]
    assert len(said) == 1 and "On this virtual clock its twin (spectrometer) runs its steps" in said[0], said
    if driver == "acme-reader":
        return
    caplog.clear()
    code, out, said_too = invoke("whatif", str(tmp_path / "lab.yaml"), "--vary", "devices.synthesiser.instances=1,2",
                                 "--seeds", "1")
    assert code == 0, said_too
    assert "*: the scenario as written" in said_too
    assert sum("its twin (spectrometer)" in r.getMessage() for r in caplog.records) == 1  # not once per variant
    code, _, said_too = invoke("run", str(tmp_path / "lab.yaml"), "--clock", "virtual", "--budget", "2",
                               "--journal", str(tmp_path / "v.db"))
    assert code == 0 and "twins stand in: reader by spectrometer" in said_too, said_too
    code, _, said_too = invoke("run", str(tmp_path / "lab.yaml"), "--journal", str(tmp_path / "s.db"))
    assert code == 2 and "devices.reader.driver" in said_too and "labtwin_acme_absent" in said_too
