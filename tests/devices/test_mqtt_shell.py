"""docs/mqtt.md suffices: an instrument made only of mosquitto_sub/mosquitto_pub shell commands
(examples/mqtt_shell_instrument.sh) runs a campaign, and says offline when it exits."""

import asyncio
import json
import shutil
import subprocess

import pytest

from tests.devices.test_mqtt import ROOT, mqtt_lab, prefix  # noqa: F401 (a fixture)
from tests.devices.test_mqtt_protocol import _retained
from twin.campaign.journal_read import read_events
from twin.runtime.lab import run
from twin.scenario import parse

pytestmark = [pytest.mark.process,
              pytest.mark.skipif(shutil.which("mosquitto_pub") is None, reason="needs mosquitto-clients "
                                 "(scripts/test installs it)")]


def shell_instrument(broker: str, topic: str, seconds: float) -> subprocess.Popen:
    host, _, port = broker.rpartition(":")
    proc = subprocess.Popen(["sh", "examples/mqtt_shell_instrument.sh", host, port, topic, str(seconds)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, start_new_session=True)
    assert proc.stdout.readline().decode().startswith("ready"), proc.stderr.read().decode()
    return proc


def test_a_shell_instrument_runs_a_campaign_and_says_offline_when_it_exits(mosquitto, prefix, tmp_path):
    topic = f"{prefix}/spectrometer"
    proc = shell_instrument(mosquitto, topic, 0.2)
    lab = mqtt_lab(mosquitto, prefix, **{"devices.spectrometer.instances": 1, "campaign.budget": 3})
    try:
        summary = run(parse(lab), journal=tmp_path / "j.db")
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert summary.done == 3 and summary.failed_attempts == 0, summary
    results = [json.loads(e["detail"])["body"] for e in read_events(tmp_path / "j.db", "msg.result")
               if e["device"] == "spectrometer"]
    assert len(results) == 3
    for r in results:  # it read the peak out of the sample it was sent, and handed the sample back whole
        assert r["outputs"]["peak_nm"] == r["sample"]["peak_nm"] and r["sample"]["id"].startswith("c1/e")
    assert asyncio.run(_retained(mosquitto, f"{topic}/status")) == "offline"
