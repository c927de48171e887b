"""The set-up both of the README's commands source (scripts/_venv.sh): two started together on a fresh clone do
not both make .venv — the second waits for the first's set-up, then reuses it. And scripts/test's two pytest runs
both stop at a Ctrl-C."""

import fcntl
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_a_second_set_up_waits_for_the_first_and_then_reuses_its_venv(tmp_path):
    (tmp_path / "scripts").mkdir()
    shutil.copy(ROOT / "scripts" / "_venv.sh", tmp_path / "scripts")
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    venv = tmp_path / ".venv"
    (venv / "bin").mkdir(parents=True)
    fake = venv / "bin" / "python"  # not a real one: whatever the script asks of it does nothing
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    stamp = subprocess.run(["sha256sum", "pyproject.toml"], cwd=tmp_path, capture_output=True, text=True,
                           check=True).stdout[:16]
    with open(venv / ".setup.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # a first set-up, still installing
        second = subprocess.Popen(["bash", "-c", "source scripts/_venv.sh && echo set-up done"], cwd=tmp_path,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert second.stderr.readline() == "labtwin: waiting for another set-up of .venv to finish\n"
            (venv / f".labtwin-{stamp}").touch()  # the first one's install done
            assert second.poll() is None
        finally:
            fcntl.flock(held, fcntl.LOCK_UN)
    out, err = second.communicate(timeout=60)
    assert second.returncode == 0 and out == "set-up done\n", err
    assert "installing" not in err and "creating" not in err  # it found the first one's .venv and stamp


FAKE_PYTEST = """#!/bin/bash
case "$*" in *"-m pytest"*) ;; *) exit 0 ;; esac  # the set-up's questions
case "$*" in *"process or wall"*) name=beside ;; *) name=rest ;; esac
trap 'kill "$!"; echo interrupted > "$name"; exit 130' INT
echo "$$" > "$name.pid"
sleep 60 > /dev/null 2>&1 &
wait "$!"
echo "ran to its end" > "$name"
"""


@pytest.mark.process
def test_ctrl_c_stops_both_of_the_test_scripts_pytest_runs(tmp_path):
    """scripts/test runs one pytest in the background beside another: a command a script runs in the background
    ignores Ctrl-C, and that pytest went on for minutes after the script had ended."""
    import os
    import signal
    import time

    (tmp_path / "scripts").mkdir()
    for name in ("test", "_venv.sh", "_mosquitto.sh"):
        shutil.copy(ROOT / "scripts" / name, tmp_path / "scripts")
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    (tmp_path / ".venv" / "bin").mkdir(parents=True)
    fake = tmp_path / ".venv" / "bin" / "python"  # the set-up's questions answered; `-m pytest` waits a minute
    fake.write_text(FAKE_PYTEST)
    fake.chmod(0o755)
    stamp = subprocess.run(["sha256sum", "pyproject.toml"], cwd=tmp_path, capture_output=True, text=True,
                           check=True).stdout[:16]
    (tmp_path / ".venv" / f".labtwin-{stamp}").touch()
    script = subprocess.Popen(["bash", "scripts/test"], cwd=tmp_path, start_new_session=True, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as a terminal's
    try:
        deadline = time.monotonic() + 30  # wall time of OS processes
        while not all((tmp_path / f"{n}.pid").exists() for n in ("beside", "rest")):
            assert script.poll() is None and time.monotonic() < deadline
            time.sleep(0.02)
        os.killpg(script.pid, signal.SIGINT)  # Ctrl-C: the terminal's foreground process group
        script.communicate(timeout=30)
    finally:
        if script.poll() is None:
            os.killpg(script.pid, signal.SIGKILL)
    assert script.returncode == 130
    assert (tmp_path / "rest").read_text() == "interrupted\n"
    assert (tmp_path / "beside").read_text() == "interrupted\n"
