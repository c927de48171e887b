"""A device written from docs/wire.md alone — its Python block, run as it stands, using nothing of labtwin —
serves a live campaign over Zenoh."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from twin.campaign.journal import read_events
from twin.runtime.lab import make_clock, prepare, run_async

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
SPEED = 100.0  # lab seconds per wall second


def documented_device() -> str:
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "wire.md").read_text(), re.S)
    assert len(blocks) == 1, "docs/wire.md has one Python block: the device"
    assert "twin" not in re.findall(r"^(?:import|from) (\w+)", blocks[0], re.M)
    return blocks[0]


def test_the_documented_device_measures_every_experiment_of_a_live_campaign(tmp_path):
    port = free_port()
    raw = qd_lab(**{
        "lab": f"wire{port}",
        "campaign.budget": 4,
        "devices.spectrometer.instances": 1,
        "devices.spectrometer.duration": {"mean_s": 50, "cv": 0.0},
        "devices.synthesiser.duration": {"mean_s": 30, "cv": 0.0},
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [f"tcp/127.0.0.1:{port}"]},
        "orchestrator.startup_s": 3000,
    })
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    script = tmp_path / "device.py"
    script.write_text(documented_device())
    s = prepare(path)
    clock = make_clock(s)
    db = tmp_path / "j.db"
    device = subprocess.Popen([sys.executable, str(script), s.lab, "spectrometer", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        summary = clock.run(run_async(s, clock, db, {"spectrometer"}))
    finally:
        device.terminate()
        _, err = device.communicate(timeout=30)
    assert device.returncode == 0, err  # SIGTERM: the token undeclared and the session closed, as documented
    assert summary.done == 4 and summary.abandoned == 0, summary
    assert summary.invalid_messages == 0 and summary.rejected_messages == 0 and summary.failed_attempts == 0
    events = read_events(db)
    results = [e for e in events if e["kind"] == "msg.result" and e["device"] == "spectrometer"]
    made = {e["task"].split("s")[0]: json.loads(e["detail"])["body"]["sample"]
            for e in events if e["kind"] == "msg.result" and e["device"] == "synthesiser"}
    assert len(results) == 4
    for r in results:  # what the device read off each sample is what the lab scored
        body = json.loads(r["detail"])["body"]
        sample = made[r["task"].split("s")[0]]
        assert body["outputs"] == {"peak_nm": sample["peak_nm"], "fwhm_nm": sample["fwhm_nm"],
                                   "intensity": sample["amplitude"]}
        assert body["sample"]["id"].endswith(f"/e{r['experiment']}")  # the id the lab gave it, handed back
    accepted = [e for e in events if e["kind"] == "msg.accepted" and e["device"] == "spectrometer"]
    assert len(accepted) == 4
