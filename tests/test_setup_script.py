"""The set-up both of the README's commands source (scripts/_venv.sh): two started together on a fresh clone do
not both make .venv — the second waits for the first's set-up, then reuses it."""

import fcntl
import shutil
import subprocess
from pathlib import Path

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
