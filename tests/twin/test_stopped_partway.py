"""Long commands stopped partway by Ctrl-C or SIGTERM: a bench, a shapes bench, a what-if and a route bench each
print the table of what they finished (the seeds, shapes or targets every row finished), say so, and write no
file of a part of their runs."""

import subprocess
import sys
from pathlib import Path

import pytest

from twin.core.counts import counted

ROOT = Path(__file__).resolve().parents[2]


def _stopped_when(args: list[str], enough, stop: int) -> tuple[int, str, str]:
    """`twin ARGS` sent ``stop`` once its progress (stderr, a line every half second off a terminal) has a line
    that is ``enough``: its exit status, stdout and stderr."""
    import os
    import re
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "twin", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=ROOT, start_new_session=True,
                            env={**os.environ, "COLUMNS": "120", "LABTWIN_PROGRESS_S": "0.5"})
    said = []
    try:
        for line in proc.stderr:
            said.append(line)
            done = re.search(r" (\d+)/\d+ ", line)
            if done and enough(int(done.group(1))):
                break
        if stop == signal.SIGINT:
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole group
        else:
            proc.send_signal(stop)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode, out, "".join(said) + err


@pytest.mark.process
def test_a_bench_stopped_partway_shows_the_seeds_every_scheduler_finished(tmp_path):
    import re
    import signal

    csv = tmp_path / "runs.csv"
    code, out, err = _stopped_when(["bench", "schedulers", "scenarios/flaky_lab.yaml", "--seeds", "400",
                                    "--schedulers", "fifo,spt", "--csv", str(csv)], lambda done: done >= 6,
                                   signal.SIGINT)
    assert code == 130, err
    title = re.search(r"flaky_lab —\s+(\d+)\s+of\s+400\s+runs\s+per\s+scheduler", out)
    assert title and 3 <= int(title.group(1)) < 400, out
    assert re.search(r"^fifo +\d+\.\d+", out, re.M) and re.search(r"^spt +\d+\.\d+", out, re.M), out
    assert f"interrupted: the table is of the {_seeds(title)} of flaky_lab every scheduler finished" in err
    assert "Traceback" not in err and not csv.exists()  # no file of a part of the runs


@pytest.mark.process
def test_a_shapes_bench_stopped_partway_shows_the_shapes_it_finished():
    import re
    import signal

    code, out, err = _stopped_when(["bench", "schedulers", "scenarios/flaky_lab.yaml", "--shapes", "--seeds", "10",
                                    "--schedulers", "fifo,spt"], lambda done: done >= 1, signal.SIGTERM)
    assert code == 143, err
    shown = re.search(r"(\d+)\s+of\s+(\d+)\s+shapes", out)  # the title wraps to a table of one shape's width
    assert shown and 1 <= int(shown.group(1)) < int(shown.group(2)), out
    assert "as written" in out
    assert (f"terminated (SIGTERM): the table is of the {counted(int(shown.group(1)), 'shape', 'shapes')} of "
            f"{shown.group(2)} finished") in err


@pytest.mark.process
def test_a_whatif_stopped_partway_shows_the_seeds_every_variant_finished_and_writes_no_file(tmp_path):
    import re
    import signal


    csv = tmp_path / "w.csv"
    code, out, err = _stopped_when(["whatif", "scenarios/flaky_lab.yaml", "--vary", "devices.reactor.instances=2,3",
                                    "--seeds", "300", "--csv", str(csv)], lambda done: done >= 4, signal.SIGINT)
    assert code == 130, err
    title = re.search(r"2\s+variants\s+×\s+(\d+)\s+of\s+300\s+seeds", out)
    assert title and 1 <= int(title.group(1)) < 300, out
    assert f"Medians and IQR over {title.group(1)} paired seeds" in " ".join(out.split())
    assert f"interrupted: the table is of the {_seeds(title)} every variant finished" in err
    assert not csv.exists() and "Traceback" not in err


@pytest.mark.process
def test_a_route_bench_stopped_partway_shows_the_targets_every_method_finished():
    import re
    import signal


    code, out, err = _stopped_when(["bench", "routes", "--targets", "100", "--seconds", "1", "--methods",
                                    "breadth-first,random"], lambda done: done >= 4, signal.SIGINT)
    assert code == 130, err
    title = re.search(r"(\d+)\s+of\s+100\s+held-out\s+targets,\s+1\s+s\s+each", out)
    assert title and 1 <= int(title.group(1)) < 100, out
    assert re.search(r"^breadth-first +\d+", out, re.M) and re.search(r"^random +\d+", out, re.M), out
    assert (f"interrupted: the table is of the {counted(int(title.group(1)), 'target', 'targets')} every method "
            "finished") in err


def _seeds(title):
    return counted(int(title.group(1)), "seed", "seeds")


@pytest.mark.process
def test_a_stop_while_cp_sat_solves_a_shops_bound_ends_the_bench_at_once(tmp_path):
    """The bound was solved in the command's own process, where CP-SAT's C++ does not look at signals: a SIGTERM
    waited up to the solve's 120 s. Sent to the whole group (`timeout`, a CI runner), as here, it also ended the
    idle workers first, and the next run's submission was a BrokenProcessPool traceback."""
    import os
    import random
    import signal
    import time

    rng = random.Random(3)
    rows = [" ".join(f"{m} {rng.randint(1, 99)}" for m in rng.sample(range(20), 20)) for _ in range(30)]
    (tmp_path / "big.txt").write_text("30 20\n" + "\n".join(rows) + "\n")  # a proof takes hours
    proc = subprocess.Popen([sys.executable, "-m", "twin", "bench", "schedulers", "scenarios/jobshop.yaml",
                             "--jobshop", str(tmp_path / "big.txt"), "--schedulers", "mwkr"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            start_new_session=True)
    try:
        for line in proc.stderr:
            if "CP-SAT solving the shop for the bound" in line:
                break
        time.sleep(1)  # wall time, in another process: the solve under way
        stopped = time.monotonic()
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - stopped
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143 and "terminated (SIGTERM)" in err and "Traceback" not in err, err
    assert took < 30, took  # the pool's STOP_S for a worker inside the solve, not the solve's 120 s
