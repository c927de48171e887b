"""The MQTT adapter against a mosquitto with TLS, passwords and a per-instrument ACL (docs/security.md's)."""

import asyncio
import json
import os
import subprocess
import sys
import uuid
from pathlib import Path

import aiomqtt
import pytest

from tests.conftest import qd_lab, start_mosquitto
from tests.devices.test_mqtt import SPEED
from twin.campaign.journal_read import read_events
from twin.core.errors import DriverError
from twin.runtime.assembly import load_driver
from twin.runtime.lab import run
from twin.scenario import parse
from twin.tools.security_init import init

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
PASSWORDS = {"lab": "lab-secret", "instrument": "instrument-secret", "intruder": "intruder-secret"}
ACL = """\
user lab
topic write sec/+/+/command
topic read sec/+/+/result
topic read sec/+/+/status
topic read sec/+/+/progress
topic read sec/+/+/telemetry
topic read sec/+/+/health

user instrument
topic read sec/+/+/command
topic write sec/+/+/result
topic readwrite sec/+/+/status
topic write sec/+/+/progress
topic write sec/+/+/telemetry
topic write sec/+/+/health

user intruder
topic read sec/+/+/result
"""


@pytest.fixture(scope="module")
def broker(tmp_path_factory):
    """mosquitto on loopback: TLS with a certificate from `twin security init`, passwords, the ACL above."""
    d = tmp_path_factory.mktemp("secure-mosquitto")
    init(d / "pki", "mq", [])
    other = d / "other-pki"
    init(other, "mq", [])
    pw = d / "passwords"
    for i, (user, secret) in enumerate(PASSWORDS.items()):
        subprocess.run(["mosquitto_passwd", "-b", *(["-c"] if i == 0 else []), str(pw), user, secret], check=True,
                       capture_output=True)
    (d / "acl").write_text(ACL)
    d_pki = d / "pki"
    proc, port = start_mosquitto(d, f"per_listener_settings false\nallow_anonymous false\npassword_file {pw}\n"
                                    f"acl_file {d / 'acl'}\ncafile {d_pki / 'ca.pem'}\n"
                                    f"certfile {d_pki / 'router' / 'cert.pem'}\nkeyfile {d_pki / 'router' / 'key.pem'}\n")
    yield {"address": f"127.0.0.1:{port}", "ca": str(d / "pki" / "ca.pem"), "other_ca": str(other / "ca.pem")}
    proc.terminate()
    proc.wait(timeout=10)


def lab(broker, prefix, **options):
    o = {"broker": broker["address"], "topic": f"{prefix}/{{name}}", "steps": ["measure"], "username": "lab",
         "password_env": "LAB_MQTT_PASSWORD", "tls": {"ca": broker["ca"]}, **options}
    return parse(qd_lab(**{
        "devices.spectrometer": {"driver": "mqtt", "instances": 1, "steps": ["measure"],
                                 "duration": {"mean_s": 60, "cv": 0}, "options": o},
        "clock": {"mode": "scaled", "speed": SPEED}, "orchestrator.startup_s": 1000, "campaign.budget": 3,
    }))


@pytest.fixture
def prefix(monkeypatch):
    monkeypatch.setenv("LAB_MQTT_PASSWORD", PASSWORDS["lab"])
    return f"sec/{uuid.uuid4().hex[:8]}"


async def _connect(driver):
    await driver.connect(lambda present: None)
    await driver.disconnect()


@pytest.mark.parametrize("options, words", [
    ({"username": "lab", "password_env": None, "password": "wrong"}, "refused user 'lab'"),
    ({"username": None, "password_env": None}, "refused an anonymous client"),
    ({"tls": {"ca": "OTHER"}}, "TLS handshake"),
    ({"tls": None, "connect_timeout_s": 2}, "cannot reach"),  # a TLS port never answers plain MQTT
    ({"password_env": "NOT_SET_ANYWHERE"}, "$NOT_SET_ANYWHERE, which is not set"),
    ({"tls": {"ca": "/no/such/ca.pem"}}, "options.tls.ca"),
])
def test_a_refused_connection_says_why_and_what_to_check(broker, prefix, options, words):
    if options.get("tls") and options["tls"].get("ca") == "OTHER":
        options = {**options, "tls": {"ca": broker["other_ca"]}}
    s = lab(broker, prefix, **options)
    with pytest.raises(DriverError, match=words.replace("$", r"\$").replace("(", r"\(")):
        asyncio.run(_connect(load_driver(s, "spectrometer", "spectrometer")))


def test_an_instrument_behind_tls_and_its_acl_measures_and_an_intruder_counts_for_nothing(broker, prefix, tmp_path):
    topic = f"{prefix}/spectrometer"
    env = {**os.environ, "INSTRUMENT_PASSWORD": PASSWORDS["instrument"]}
    proc = subprocess.Popen([sys.executable, "examples/mqtt_instrument.py", "--broker", broker["address"],
                             "--topic", topic, "--seconds", "0.2", "--username", "instrument",
                             "--password-env", "INSTRUMENT_PASSWORD", "--ca", broker["ca"]],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, env=env)
    assert proc.stdout.readline().decode().startswith("ready"), proc.stderr.read().decode()
    seen: list[str] = []

    async def intruder(stop):
        host, port = broker["address"].split(":")
        async with aiomqtt.Client(host, int(port), username="intruder", password=PASSWORDS["intruder"],
                                  tls_params=aiomqtt.TLSParameters(ca_certs=broker["ca"])) as c:
            await c.subscribe(f"{topic}/#")  # the ACL lets it read results, not commands

            async def listen():
                async for msg in c.messages:
                    seen.append(str(msg.topic))

            listening = asyncio.ensure_future(listen())
            n = 0
            while not stop.is_set():
                n += 1
                forged = {"id": f"spectrometer-{n % 5}", "outputs": {"peak_nm": 999.0}, "sample": {}}
                await c.publish(f"{topic}/result", json.dumps(forged))  # the ACL drops it at the broker
                await asyncio.sleep(0.05)
            listening.cancel()

    def campaign():
        async def both():
            stop = asyncio.Event()
            spy = asyncio.ensure_future(intruder(stop))
            try:
                return await asyncio.to_thread(run, lab(broker, prefix), journal=tmp_path / "j.db")
            finally:
                stop.set()
                await spy
        return asyncio.run(both())

    try:
        summary = campaign()
    finally:
        proc.terminate()
        proc.wait()
    assert summary.done == 3 and summary.failed_attempts == 0
    done = read_events(tmp_path / "j.db", "experiment.done")
    outputs = [json.loads(e["detail"])["outputs"] for e in done]
    assert len(outputs) == 3 and all("fwhm_nm" in o and o["peak_nm"] != 999.0 for o in outputs)
    assert seen and not any(t.endswith("/command") for t in seen)  # it heard results, never a command id
