import contextlib
import os
import signal
from pathlib import Path

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):
    # xdist's workers are given COLUMNS=80 and LINES=24, which a console made at import keeps for good: the tables
    # of commands run here were then 80 wide in a worker and as wide as each test asks in a plain run
    for name in ("COLUMNS", "LINES"):
        os.environ.pop(name, None)

from twin.core.bus import open_bus
from twin.core.clock import LabClock
from twin.scenario import set_dotted


def pytest_configure(config) -> None:
    """Ctrl-C as a user's shell gives it. A background command of a script (`scripts/test` runs the `process` tests
    so) starts with SIGINT ignored, and so would every process a test starts from it: the tests of what Ctrl-C does
    then passed or failed by whether an earlier test had set Ctrl-C's handler (`scripts/test -k pool` failed)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def virtual_clock() -> LabClock:
    return LabClock("virtual")


@pytest.fixture(params=["memory", "zenoh"])
def bus_kind(request) -> str:
    return request.param


@pytest.fixture
def make_bus(bus_kind):
    """Build a started bus of the parametrised kind inside a running loop."""

    async def make(clock: LabClock):
        bus = open_bus(bus_kind, clock)
        await bus.start()
        return bus

    return make


def qd_lab(**changes) -> dict:
    """A small quantum-dot lab as a scenario dict; ``changes`` are dotted paths."""
    raw = {
        "name": "test_lab",
        "lab": "t",
        "devices": {
            "synthesiser": {"driver": "synthesiser", "instances": 1, "steps": ["synthesise"],
                            "duration": {"mean_s": 60, "cv": 0.1}},
            "spectrometer": {"driver": "spectrometer", "instances": 2, "steps": ["measure"],
                             "duration": {"mean_s": 60, "cv": 0.1}},
        },
        "chemistry": {
            "model": "quantum_dots",
            "parameters": {
                "concentration_mm": {"low": 1, "high": 50},
                "temperature_c": {"low": 220, "high": 320},
                "time_s": {"low": 10, "high": 600},
            },
            "targets": [{"name": "R", "outputs": {"peak_nm": {"value": 630, "tol": 5}}}],
        },
        "workflow": [{"step": "synthesise", "device": "synthesiser"}, {"step": "measure", "device": "spectrometer"}],
        "campaign": {"budget": 8, "max_in_flight": 2, "stop_on_target": False},
        "orchestrator": {"timeout_factor": 2, "timeout_slack_s": 60,
                         "retry": {"max_attempts": 3, "backoff_s": 10, "jitter": 0.2}},
        "bus": {"kind": "memory"},
    }
    for dotted, value in changes.items():
        set_dotted(raw, dotted, value)
    return raw


def twin_cli(*args, columns: int = 200, input: str | None = None):
    """`twin ARGS` run in this process (typer's CliRunner): its exit code, stdout and stderr, without a new
    interpreter importing it all again. An uncaught exception, a traceback in a real process, fails the test.
    ``input``: its standard input."""
    from typer.testing import CliRunner

    from twin.cli import app

    res = CliRunner().invoke(app, [str(a) for a in args], input=input, env={"COLUMNS": str(columns)})
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        res.exception.add_note(f"`twin {' '.join(map(str, args))}` printed before it:\n{res.output[-2000:]}")
        raise res.exception
    return res


@pytest.fixture
def scenario_of():
    from twin.scenario import parse

    return lambda **changes: parse(qd_lab(**changes))


def start_mosquitto(directory: Path, settings: str):
    """A real mosquitto on a free loopback port with ``settings`` added to its config; returns (process, port)."""
    import shutil
    import socket
    import subprocess
    import time

    binary = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
    if binary is None:
        pytest.fail("mosquitto is not installed: apt-get install -y mosquitto (.ci/run does)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    conf = directory / "mosquitto.conf"
    # set_tcp_nodelay: without it the broker's Nagle delay put ~40 ms on every round trip; started as root,
    # mosquitto drops to the "mosquitto" user, which cannot read a test's private files: stay root
    conf.write_text(f"user root\nlistener {port} 127.0.0.1\npersistence false\nset_tcp_nodelay true\n"
                    f"log_dest file {directory / 'log'}\n{settings}")
    # SIGTERM when the test process dies, even killed (PR_SET_PDEATHSIG), where a pytest stopped by SIGKILL left its
    # brokers running; set by util-linux's setpriv, not a preexec_fn (unsafe in a process with Zenoh's threads)
    ends_with_us = [setpriv, "--pdeathsig", "TERM"] if (setpriv := shutil.which("setpriv")) else []
    proc = subprocess.Popen([*ends_with_us, binary, "-c", str(conf)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 10
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return proc, port
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                pytest.fail(f"mosquitto did not start: {proc.stderr.read().decode()[:500]}")
            time.sleep(0.05)


@pytest.fixture(scope="session")
def mosquitto(tmp_path_factory):
    """A real mosquitto broker on loopback for this test session; yields "127.0.0.1:PORT"."""
    proc, port = start_mosquitto(tmp_path_factory.mktemp("mosquitto"), "allow_anonymous true\n")
    yield f"127.0.0.1:{port}"
    proc.terminate()
    proc.wait(timeout=10)


def assert_adopted_once(events: list[dict], task: str, device: str) -> None:
    """A step that finished while its campaign was dead: its result taken once, from ``device``, after the resume,
    and the step never counted as failed."""
    done = [e for e in events if e["kind"] == "attempt.done" and e["task"] == task]
    assert len(done) == 1 and done[0]["device"] == device, "the finished result is adopted, once"
    assert done[0]["t_lab"] >= next(e["t_lab"] for e in events if e["kind"] == "campaign.resumed")
    assert not [e for e in events if e["kind"] == "attempt.failed" and e["task"] == task]


@contextlib.contextmanager
def ctrl_c_at(row: int):
    """A run inside the block gets SIGINT (Ctrl-C) when a journal of it writes its event ``row``."""
    from twin.campaign.journal import Journal

    append = Journal._append

    def interrupting(self, *r):
        if self._seq + 1 == row:
            os.kill(os.getpid(), signal.SIGINT)
        append(self, *r)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Journal, "_append", interrupting)
        yield


def pytest_collection_modifyitems(config, items) -> None:
    """A test whose source runs a lab on a scaled clock (``scaled`` in it, its parametrisation included) is marked
    ``wall``: its margins are in wall time, so `scripts/test` runs it beside the ``process`` tests, at their
    priority, not among the CPU-bound tests it lowers."""
    import inspect

    wall = pytest.mark.wall
    sources: dict = {}
    for item in items:
        function = getattr(item, "function", None)
        if function is None or item.get_closest_marker("process"):
            continue
        if function not in sources:
            try:
                sources[function] = "scaled" in inspect.getsource(function)
            except (OSError, TypeError):
                sources[function] = False
        if sources[function]:
            item.add_marker(wall)
