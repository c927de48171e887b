"""The benches' and `twin whatif`'s worker pool: Ctrl-C stops the runs going at once, and a stopped worker starts
none of the runs already queued to it."""

import contextlib
import tempfile
import time
from pathlib import Path

import pytest

from twin.tools.pool import STOP_S, WorkerPool


def _holds(path: str) -> None:
    """A run that keeps a temporary file until it ends or is stopped."""
    held = Path(path)
    try:  # made inside: a stop that lands as it is made removes it too
        held.write_text("running")
        time.sleep(60)  # wall time, in a worker process: what is measured is how it is stopped
    finally:
        held.unlink(missing_ok=True)


@pytest.mark.process
def test_ctrl_c_stops_the_runs_going_and_no_worker_starts_one_queued_to_it(tmp_path):
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        with WorkerPool(2) as pool:
            for i in range(6):  # two run, one more is queued to the workers, the rest wait in the pool
                pool.submit(_holds, str(tmp_path / f"run{i}"))
            manager = pool._executor_manager_thread
            while len(list(tmp_path.iterdir())) < 2:
                time.sleep(0.01)
            raise KeyboardInterrupt
    # a worker that went on to the queued run was killed in it when STOP_S ran out, its file left behind
    assert list(tmp_path.iterdir()) == []
    assert time.monotonic() - started < STOP_S
    # nothing of the pool runs on to race the interpreter's exit (a traceback after "interrupted")
    assert not manager.is_alive()


def _leaves(started: str) -> None:
    """A run whose temporary directory is left when it is stopped: as one stopped inside
    ``tempfile.TemporaryDirectory()`` itself, or killed, leaves its own."""
    Path(tempfile.mkdtemp(), "journal.db").write_text("running")
    Path(started, str(time.monotonic_ns())).touch()
    time.sleep(60)


@pytest.mark.process
def test_the_runs_temporary_files_go_when_the_pool_ends_however_they_were_stopped(tmp_path, monkeypatch):
    scratch, started = tmp_path / "tmp", tmp_path / "started"
    scratch.mkdir()
    started.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    with pytest.raises(KeyboardInterrupt):
        with WorkerPool(2) as pool:
            for _ in range(2):
                pool.submit(_leaves, str(started))
            while len(list(started.iterdir())) < 2:
                time.sleep(0.01)
            assert len(list(Path(pool.scratch).iterdir())) == 2  # each run's directory, in the pool's own
            raise KeyboardInterrupt
    assert list(scratch.iterdir()) == []
    with WorkerPool(1) as pool:  # and when every run ended well
        assert pool.submit(tempfile.gettempdir).result() == pool.scratch
    assert list(scratch.iterdir()) == []


STARTS_SLOWLY = """
import time
from twin.tools.pool import WorkerPool

def starts_slowly():
    time.sleep(2)  # wall time: a worker's set-up (imports, models) that a stop lands in

started = time.monotonic()
try:
    with WorkerPool(2, initializer=starts_slowly) as pool:
        for i in range(20):
            pool.submit(time.sleep, 0.1)
        time.sleep(0.5)
        raise KeyboardInterrupt
except KeyboardInterrupt:
    print(time.monotonic() - started)
"""


@pytest.mark.process
def test_a_stop_while_the_workers_start_is_quiet_and_at_once():
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", STARTS_SLOWLY], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 0 and float(done.stdout) < STOP_S, done
    assert "Traceback" not in done.stderr and "Exception in initializer" not in done.stderr, done.stderr


def _went_on(reached: list[str]) -> None:
    """A Python call: where a signal's handler runs if it was not only noted."""
    reached.append("went on")


@pytest.mark.process
@pytest.mark.parametrize("sig, raised", [("SIGINT", KeyboardInterrupt), ("SIGTERM", "Terminated")])
def test_a_signal_while_the_pool_is_open_is_raised_where_the_runs_are_waited_for(tmp_path, sig, raised):
    """Raised wherever the main thread was, a Ctrl-C or SIGTERM could land inside the executor's own locking
    (``submit``, ``as_completed``) and leave a lock held: the command then never ended."""
    import os
    import signal

    from twin.cli.stopping import Terminated, sigterm_unwinds

    expected = Terminated if raised == "Terminated" else raised
    reached: list[str] = []
    with sigterm_unwinds(), pytest.raises(expected):
        with WorkerPool(2) as pool:
            futures = [pool.submit(_holds, str(tmp_path / f"run{i}")) for i in range(4)]
            while len(list(tmp_path.iterdir())) < 2:
                time.sleep(0.01)
            os.kill(os.getpid(), getattr(signal, sig))
            _went_on(reached)
            assert reached == ["went on"]
            for _ in pool.completed(futures):
                reached.append("a run ended")
    assert reached == ["went on"] and list(tmp_path.iterdir()) == []  # raised at the wait, the runs stopped
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


SIGTERM_BY_DEFAULT = """
import os, signal, sys, time
from pathlib import Path
from twin.tools.pool import WorkerPool

def holds(path):
    Path(path).write_text("running")
    try:
        time.sleep(60)
    finally:
        Path(path).unlink()

with WorkerPool(1) as pool:
    runs = pool.map(holds, [sys.argv[1]])
    while not Path(sys.argv[1]).exists():
        time.sleep(0.01)
    os.kill(os.getpid(), signal.SIGTERM)
    print("went on", flush=True)
    list(runs)
print("not reached")
"""


@pytest.mark.process
def test_a_sigterm_left_to_the_default_ends_the_command_through_the_pool_which_stops_its_runs(tmp_path):
    import subprocess
    import sys

    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "-c", SIGTERM_BY_DEFAULT, str(run)], capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 143 and done.stdout == "went on\n", done
    assert not run.exists() and "Traceback" not in done.stderr


def _runs_then_marks(marker: str, budget: int) -> None:
    """A what-if's run of a long campaign, then a mark that it returned."""
    from twin.runtime.lab import prepare
    from twin.tools.whatif import Variant, one

    lab = prepare(Path(__file__).resolve().parents[2] / "scenarios" / "quantum_dots.yaml",
                  overrides={"campaign.budget": budget, "campaign.stop_on_target": False,
                             "campaign.planner": "random"})
    one(lab, Variant("as written", ()), 0)
    Path(marker).touch()


def _events(journal: Path) -> int:
    import sqlite3

    try:
        with contextlib.closing(sqlite3.connect(f"file:{journal}?mode=ro", uri=True)) as db:
            return int(db.execute("SELECT COUNT(*) FROM events").fetchone()[0])
    except sqlite3.Error:  # not made yet
        return 0


@pytest.mark.process
def test_a_run_stopped_in_its_campaign_ends_there_and_does_not_finish_it(tmp_path):
    """A bench's campaign in a worker took the pool's SIGTERM as its own clean stop (or, raised in the planner as
    SystemExit, as the planner's failure) and finished what was in its lab first: seconds of a stop, and a run that
    returned as if nothing had happened."""
    marker = tmp_path / "returned"
    with pytest.raises(KeyboardInterrupt):
        with WorkerPool(1) as pool:
            pool.submit(_runs_then_marks, str(marker), 400)
            while not any(_events(j) > 30 for j in Path(pool.scratch).glob("*/j.db")):  # well into its campaign
                assert not marker.exists()
                time.sleep(0.05)
            raise KeyboardInterrupt
    assert not marker.exists()


KILLED = """
import os, signal, sys, time
from pathlib import Path
from twin.tools.pool import WorkerPool

def holds(path):
    Path(path).write_text(str(os.getpid()))
    time.sleep(60)

with WorkerPool(1) as pool:
    Path(sys.argv[1] + ".scratch").write_text(pool.scratch)
    pool.submit(holds, sys.argv[1])
    while not Path(sys.argv[1]).exists() or not Path(sys.argv[1]).read_text():
        time.sleep(0.01)
    os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.process
def test_a_worker_ends_with_its_pool_even_when_that_is_killed(tmp_path):
    """SIGKILL cannot be handled: the worker was orphaned and, once its run ended, waited for work for good; and the
    runs' directory, which the pool removes as it ends, was left in /tmp."""
    import subprocess
    import sys

    run = tmp_path / "run"
    done = subprocess.run([sys.executable, "-c", KILLED, str(run)], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == -9, done
    worker = Path(f"/proc/{run.read_text()}/status")

    def alive() -> bool:
        try:
            return "zombie" not in worker.read_text()
        except FileNotFoundError:
            return False
    deadline = time.monotonic() + STOP_S
    while alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(), "the worker outlived its pool"
    assert not Path((tmp_path / "run.scratch").read_text()).exists(), "the runs' directory outlived its pool"


STOPPED_IN_A_CALLBACK = """
import os, signal, sys, weakref
from twin.tools import pool

pool._start_worker(None, sys.argv[1], os.getppid(), (), None)  # as the pool starts each worker
pool._running = True  # in a run


class Held:
    pass


def freed(_):  # as importlib's module locks are freed: Python prints what such a callback raises, and goes on
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(1000):  # the handler runs here
        pass


held = Held()
ref = weakref.ref(held, freed)
del held
print("went on")
"""


@pytest.mark.process
def test_a_stop_that_lands_in_a_callback_python_cannot_raise_from_ends_the_worker_quietly(tmp_path):
    """A whatif stopped by SIGTERM printed `Exception ignored in: <function _get_module_lock.<locals>.cb ...>` and a
    traceback from a worker whose stop landed as a module lock was freed; and that worker's run went on."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", STOPPED_IN_A_CALLBACK, str(tmp_path)], capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 143 and "went on" not in done.stdout, done
    assert "Exception ignored" not in done.stderr and "Traceback" not in done.stderr, done.stderr


def _threads() -> dict:
    import scipy.linalg  # noqa: F401  loaded in the worker, after the fork, as a GP-BO planner loads it
    from threadpoolctl import threadpool_info

    return {f"{i['internal_api']} {Path(i['filepath']).name}": i["num_threads"] for i in threadpool_info()}


def test_a_worker_runs_each_numerical_library_on_one_thread():
    """Two workers on two cores, each with a BLAS of two threads that spin a while after every call: a worker's
    decisions waited for the core its neighbour's BLAS held (a rule's 0.04 ms decision took 4 ms at the 99th
    percentile in a bench, the rl policy's 16 ms). Numpy's BLAS comes with the fork; scipy's is loaded after it."""
    import numpy  # noqa: F401  in this process, as in a bench's before its pool starts
    from threadpoolctl import threadpool_info

    here = {i["internal_api"] for i in threadpool_info()}
    with WorkerPool(1) as pool:
        there = pool.submit(_threads).result()
    assert {name.split()[0] for name in there} >= here | {"openblas"}, there
    assert set(there.values()) == {1}, there
