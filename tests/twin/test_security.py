"""A real `twin router --security` with certificates from `twin security init`: who may say and read what."""

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
import zenoh

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from twin.campaign.journal_read import read_events
from twin.core import keys
from twin.core.bus.security import Identity, access_control, check_listen, session_config
from twin.core.errors import BusError, TwinError
from twin.runtime.lab import make_clock, prepare, run_async
from twin.tools.security_init import init

pytestmark = pytest.mark.process
ROOT = Path(__file__).resolve().parents[2]
LAB = "t"
SPEED = 600.0


@pytest.fixture(scope="module")
def secured(tmp_path_factory):
    """A security directory for lab ``t`` (and one of another CA), and a router enforcing it."""
    tmp = tmp_path_factory.mktemp("security")
    init(tmp / "lab", LAB, ["synthesiser", "spectrometer", "spectrometer-1", "spectrometer-2"])
    init(tmp / "other", LAB, ["spectrometer-1"])  # the same names, signed by another CA
    endpoint = f"tls/127.0.0.1:{free_port()}"
    router = subprocess.Popen([sys.executable, "-m", "twin", "router", "--listen", endpoint, "--security",
                               str(tmp / "lab")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    line = router.stdout.readline().decode()
    assert line.startswith("router"), line + router.stderr.read().decode()
    yield tmp, endpoint
    router.terminate()
    router.wait(10)


def session(endpoint, config=None, timeout_ms=3000):
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("connect/timeout_ms", str(timeout_ms))
    for path, value in (config or {}).items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def as_who(secured, role, name="", directory="lab"):
    tmp, endpoint = secured
    return session(endpoint, session_config(tmp / directory, Identity(role, LAB, name)))


class Ears:
    """The orchestrator's view: every message and token under the lab's prefix."""

    def __init__(self, secured):
        self.s = as_who(secured, "orchestrator")
        self.heard, self.tokens = [], []
        self.s.declare_subscriber(f"labtwin/{LAB}/**", lambda x: self.heard.append((str(x.key_expr),
                                                                                    x.payload.to_bytes())))
        self.s.liveliness().declare_subscriber(f"labtwin/{LAB}/alive/**",
                                               lambda x: self.tokens.append(str(x.key_expr)))

    def close(self):
        self.s.close()


def lab_file(tmp_path, **changes):
    """The test lab (lab ``t``), with ``changes``, as a scenario file."""
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump({**qd_lab(**changes), "lab": LAB}))
    return path


def settle(seconds=0.6):
    time.sleep(seconds)  # wall time: what crosses a real router


def test_without_a_certificate_or_with_another_cas_there_is_no_session(secured):
    tmp, endpoint = secured
    with pytest.raises(Exception, match="Unable to connect"):
        session(endpoint, {"transport/link/tls/root_ca_certificate": str(tmp / "lab" / "ca.pem")}, 1500)
    with pytest.raises(Exception, match="Unable to connect"):
        as_who(secured, "device", "spectrometer-1", directory="other")


def test_a_device_says_only_its_own_words_and_hears_only_its_own_commands(secured):
    ears = Ears(secured)
    own, other = as_who(secured, "device", "spectrometer-1"), as_who(secured, "device", "spectrometer-2")
    commands, overheard = [], []
    own.declare_subscriber(keys.cmd(LAB, "spectrometer-1"), lambda x: commands.append(x.payload.to_bytes()))
    own.declare_subscriber(f"labtwin/{LAB}/**", lambda x: overheard.append(x.payload.to_bytes()))
    settle()
    try:
        own.put(keys.evt(LAB, "spectrometer-1"), b"mine")  # the control: allowed, and heard
        other.put(keys.evt(LAB, "spectrometer-1"), b"forged by spectrometer-2")
        other.put(keys.telemetry(LAB, "spectrometer-1"), b"forged")
        other.put(keys.cmd(LAB, "spectrometer-1"), b"a forged command")
        other.put(keys.campaign(LAB, "c1", "decisions"), b"a forged decision")
        token = other.liveliness().declare_token(keys.alive(LAB, "spectrometer-1"))
        ears.s.put(keys.cmd(LAB, "spectrometer-1"), b"a real command")
        ears.s.put(keys.cmd(LAB, "spectrometer-2"), b"not for spectrometer-1")
        ears.s.put(keys.evt(LAB, "synthesiser"), b"not for spectrometer-1 either")
        settle()
        ours = {b"a real command", b"not for spectrometer-1", b"not for spectrometer-1 either"}
        assert [(k, p) for k, p in ears.heard if p not in ours] == [(keys.evt(LAB, "spectrometer-1"), b"mine")]
        assert ears.tokens == []  # spectrometer-2 cannot declare spectrometer-1's presence
        assert commands == [b"a real command"]  # not spectrometer-2's forgery
        assert overheard == [b"mine", b"a real command"]  # what its session may receive: nothing of the rest of the lab
        replies = list(other.get(keys.campaign(LAB, "c1", "history"), timeout=1.0))
        assert replies == []  # the history is not a device's to read
        token.undeclare()
    finally:
        for s in (own, other):
            s.close()
        ears.close()


def test_a_watcher_reads_everything_and_can_do_nothing_else(secured):
    ears = Ears(secured)
    watcher = as_who(secured, "watcher")
    seen = []
    watcher.declare_subscriber(f"labtwin/{LAB}/**", lambda x: seen.append(str(x.key_expr)))
    history = ears.s.declare_queryable(keys.campaign(LAB, "c1", "history"), lambda q: q.reply(q.key_expr, b"[]"))
    settle()
    try:
        ears.s.put(keys.evt(LAB, "synthesiser"), b"a result")
        watcher.put(keys.evt(LAB, "synthesiser"), b"forged by the watcher")
        watcher.put(keys.cmd(LAB, "synthesiser"), b"a forged command")
        token = watcher.liveliness().declare_token(keys.alive(LAB, "synthesiser"))
        answers = [r.ok.payload.to_bytes() for r in watcher.get(keys.campaign(LAB, "c1", "history"), timeout=2.0)
                   if r.ok is not None]
        settle()
        assert answers == [b"[]"]
        assert keys.evt(LAB, "synthesiser") in seen
        assert [p for _, p in ears.heard] == [b"a result"]  # its own, heard locally; nothing from the watcher
        assert ears.tokens == []
        token.undeclare()
    finally:
        history.undeclare()
        watcher.close()
        ears.close()


def test_a_campaign_with_an_external_device_runs_end_to_end_over_mutual_tls(secured, tmp_path):
    tmp, endpoint = secured
    path = lab_file(tmp_path, **{
        "campaign.budget": 3, "campaign.max_in_flight": 1,
        "devices.synthesiser.duration": {"mean_s": 60, "cv": 0.0},
        "devices.spectrometer.duration": {"mean_s": 60, "cv": 0.0},
        "devices.spectrometer.instances": 1,
        "clock": {"mode": "scaled", "speed": SPEED},
        "bus": {"kind": "zenoh", "listen": [], "connect": [endpoint], "security": str(tmp / "lab")},
        "orchestrator.startup_s": 6000,
    })
    s = prepare(path)
    clock = make_clock(s)
    spec = s.model_copy(update={"bus": s.bus.model_copy(update={"listen": []})})
    device = subprocess.Popen([sys.executable, "-m", "twin", "device", "serve", str(path), "--id", "spectrometer",
                               "--connect", endpoint, "--clock", "scaled", "--speed", str(SPEED)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    try:
        line = device.stdout.readline().decode()
        assert line.startswith("ready spectrometer"), line + device.stderr.read().decode()
        # the same device served again with its certificate: the policy lets it see the first one's token
        again = subprocess.run([sys.executable, "-m", "twin", "device", "serve", str(path), "--id", "spectrometer",
                                "--connect", endpoint, "--clock", "scaled", "--speed", str(SPEED)],
                               capture_output=True, text=True, cwd=ROOT, timeout=60)
        summary = clock.run(run_async(spec, clock, tmp_path / "j.db", {"spectrometer"}))
    finally:
        device.terminate()
        device.wait(10)
    assert again.returncode == 2 and "device spectrometer of lab" in again.stderr, again.stderr
    assert summary.done == 3 and summary.rejected_messages == 0
    assert len(read_events(tmp_path / "j.db", "msg.result")) == 6
    assert read_events(tmp_path / "j.db", "device.mismatch") == []  # served from the lab's own file


def test_the_policy_gives_each_device_only_its_own_keys():
    acl = access_control("lab", ["a", "b"])
    assert acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    by_subject = {p["subjects"][0]: [k for r in p["rules"] for k in rules[r]["key_exprs"]] for p in acl["policies"]}
    assert all("/b/" not in k and "/b" != k[-2:] for k in by_subject["device0"])
    # a scheduler agent follows the lab's clock, asked again when its campaign comes (twin.runtime.labtime)
    assert {"labtwin/lab/clock", "labtwin/lab/orchestrator/alive"} <= set(by_subject["scheduler"])
    assert all(k.startswith(("labtwin/lab/agent/", "labtwin/lab/clock", "labtwin/lab/orchestrator",
                             "labtwin/lab/claim/agent/")) for k in by_subject["scheduler"])
    assert {s["cert_common_names"][0] for s in acl["subjects"]} >= {"device.a.lab", "device.b.lab", "watcher.lab"}


def test_listening_beyond_loopback_needs_security_or_insecure():
    assert check_listen(["tcp/127.0.0.1:7447", "tcp/[::1]:7447"], secure=False, insecure=False, what="x") == []
    with pytest.raises(BusError, match=r"refusing to listen on .*0\.0\.0\.0.*`twin security init`"):
        check_listen(["tcp/0.0.0.0:7447"], secure=False, insecure=False, what="twin router")
    (warning,) = check_listen(["tcp/0.0.0.0:7447"], secure=False, insecure=True, what="twin router")
    assert "WITHOUT security" in warning and "forge" in warning
    with pytest.raises(BusError, match="tls/HOST:PORT"):
        check_listen(["tcp/10.0.0.5:7447"], secure=True, insecure=False, what="twin router")
    assert check_listen(["tls/0.0.0.0:7447"], secure=True, insecure=False, what="twin router") == []


def test_twin_router_refuses_an_open_address_without_security():
    out = subprocess.run([sys.executable, "-m", "twin", "router", "--listen", f"tcp/0.0.0.0:{free_port()}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 2 and "refusing to listen" in out.stderr and "Traceback" not in out.stderr


def test_a_missing_certificate_names_the_command_that_makes_it(secured, tmp_path):
    tmp, _ = secured
    with pytest.raises(BusError, match=r"no certificate for the device spectrometer-9 .* --device spectrometer-9"):
        session_config(tmp / "lab", Identity("device", LAB, "spectrometer-9"))
    with pytest.raises(BusError, match="made for lab 't', not 'elsewhere'"):
        session_config(tmp / "lab", Identity("device", "elsewhere", "spectrometer-1"))
    with pytest.raises(BusError, match="not a lab security directory"):
        session_config(tmp_path, Identity("orchestrator", LAB))


def test_a_scheduler_agent_answers_the_lab_and_can_do_nothing_else(secured):
    ears = Ears(secured)
    agent = as_who(secured, "scheduler")
    decide = f"labtwin/{LAB}/agent/scheduler/decide"
    q = agent.declare_queryable(decide, lambda query: query.reply(query.key_expr, b'{"assign": []}'))
    settle()
    try:
        answers = [r.ok.payload.to_bytes() for r in ears.s.get(decide, timeout=2.0) if r.ok is not None]
        agent.put(keys.evt(LAB, "synthesiser"), b"forged by the scheduler")
        agent.put(keys.cmd(LAB, "synthesiser"), b"a command from the scheduler")
        settle()
        assert answers == [b'{"assign": []}']
        assert ears.heard == []
    finally:
        q.undeclare()
        agent.close()
        ears.close()


def test_twin_run_and_twin_watch_with_security_flags_through_the_secure_router(secured, tmp_path):
    from tests.rrd import read_rrd

    tmp, endpoint = secured
    # long enough (~6 s) for a watcher that asks for the history every 2.5 s to find the lab alive
    path = lab_file(tmp_path, **{"campaign.budget": 4, "clock": {"mode": "scaled", "speed": 500.0},
                                 "bus": {"kind": "zenoh", "listen": []}})
    twin = [sys.executable, "-m", "twin"]
    watcher = subprocess.Popen([*twin, "watch", "--lab", LAB, "--connect", endpoint, "--security", str(tmp / "lab"),
                                "--save", str(tmp_path / "w.rrd")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, cwd=ROOT)
    try:
        assert watcher.stdout.readline().startswith("watching"), watcher.stderr.read()
        lab = subprocess.run([*twin, "run", str(path), "--connect", endpoint, "--security", str(tmp / "lab"),
                              "--journal", str(tmp_path / "j.db"), "--quiet"], capture_output=True, text=True,
                             cwd=ROOT, timeout=120)
        assert lab.returncode == 0, lab.stderr
        _, werr = watcher.communicate(timeout=60)
        assert watcher.returncode == 0, werr
    finally:
        watcher.kill()
    rrd = read_rrd(tmp_path / "w.rrd")
    assert "4 done" in rrd["summary"][0]["TextDocument:text"][0]


def test_a_wrong_endpoint_is_named_within_seconds(tmp_path):
    path = lab_file(tmp_path, **{"bus": {"kind": "zenoh", "listen": [], "connect": [f"tcp/127.0.0.1:{free_port()}"],
                                         "connect_timeout_ms": 1000}, "clock": {"mode": "scaled", "speed": 100.0}})
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "twin", "run", str(path), "--journal", str(tmp_path / "j.db")],
                         capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 2 and "nothing answered at tcp/127.0.0.1:" in out.stderr and "Traceback" not in out.stderr
    assert time.monotonic() - t0 < 15


def test_only_the_operator_may_ask_the_control_desk_and_it_can_do_nothing_else(secured):
    ears = Ears(secured)
    desk = ears.s.declare_queryable(keys.control(LAB, "*"), lambda q: q.reply(q.key_expr, b'{"ok": true}'))
    operator, watcher = as_who(secured, "operator"), as_who(secured, "watcher")
    device = as_who(secured, "device", "spectrometer-1")
    settle()
    try:
        def ask(session):
            return [r.ok.payload.to_bytes() for r in session.get(keys.control(LAB, "pause"), payload=b"{}",
                                                                 timeout=1.5) if r.ok is not None]

        assert ask(operator) == [b'{"ok": true}']
        assert ask(watcher) == [] and ask(device) == []  # reading the lab is not operating it
        operator.put(keys.cmd(LAB, "synthesiser"), b"a command from the operator")
        operator.put(keys.evt(LAB, "synthesiser"), b"forged by the operator")
        settle()
        assert ears.heard == []
    finally:
        desk.undeclare()
        for s in (operator, watcher, device):
            s.close()
        ears.close()


def test_twin_ctl_as_the_operator_pauses_and_stops_a_campaign_through_the_secure_router(secured, tmp_path):
    from twin.tools.control import request

    tmp, endpoint = secured
    path = lab_file(tmp_path, **{"campaign.budget": 50, "clock": {"mode": "scaled", "speed": 100.0},
                                 "bus": {"kind": "zenoh", "listen": []}})
    db = tmp_path / "j.db"
    lab = subprocess.Popen([sys.executable, "-m", "twin", "run", str(path), "--connect", endpoint, "--security",
                            str(tmp / "lab"), "--journal", str(db), "--quiet"], stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, cwd=ROOT)
    try:
        deadline, answer = time.monotonic() + 60, None
        while answer is None:  # the campaign is starting: until its desk answers
            try:
                answer = request(LAB, "pause", {"who": "alice"}, [endpoint], str(tmp / "lab"), wait_s=1.0)
            except TwinError:
                assert time.monotonic() < deadline, "the campaign's desk never answered through the router"
        assert answer["ok"] and answer["status"]["paused_by"] == "alice"
        assert request(LAB, "stop", {"who": "alice"}, [endpoint], str(tmp / "lab"))["ok"]
        assert lab.wait(timeout=60) == 0, lab.stderr.read().decode()[-2000:]
    finally:
        if lab.poll() is None:
            lab.kill()
            lab.wait()
    assert [e["kind"] for e in read_events(db) if e["kind"].startswith("operator.")] == ["operator.pause",
                                                                                         "operator.stop"]


def test_a_damaged_or_expired_certificate_is_named_with_how_to_make_it_again(tmp_path):
    """Zenoh said "peer sent no certificates at /root/.cargo/git/checkouts/...": now the file and the fix."""
    import datetime
    import shutil

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    root = tmp_path / "lab"
    init(root, LAB, ["spectrometer-1"])
    device = Identity("device", LAB, "spectrometer-1")
    (device.folder(root) / "cert.pem").write_text("copied from a chat window\n")
    with pytest.raises(BusError, match=r"cert.pem: not a PEM certificate \(overwritten or cut short\).*remove "
                                       r".*spectrometer-1 and make it again with `twin security init .* --lab t "
                                       r"--device spectrometer-1`"):
        session_config(root, device)
    shutil.rmtree(device.folder(root))  # as it says
    init(root, LAB, ["spectrometer-1"])
    assert session_config(root, device)
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "old")])
    now = datetime.datetime.now(datetime.timezone.utc)
    old = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
           .serial_number(1).not_valid_before(now - datetime.timedelta(days=400))
           .not_valid_after(now - datetime.timedelta(days=35)).sign(key, hashes.SHA256()))
    from cryptography.hazmat.primitives.serialization import Encoding

    (root / "ca.pem").write_bytes(old.public_bytes(Encoding.PEM))
    with pytest.raises(BusError, match=r"ca.pem: the certificate expired on .* UTC.*remove .*lab and make them "
                                       r"all again"):
        session_config(root, device)


def test_nothing_answering_over_tls_names_the_router_certificates_hosts_too(tmp_path):
    """A host the router's certificate does not name fails as "Timeout!" in Zenoh, like a router that is not
    there: over TLS the error says to check the certificate's names as well, and how to add one."""
    from twin.core.bus import open_bus
    from twin.core.clock import LabClock

    init(tmp_path / "lab", LAB, [])
    clock = LabClock("wall")

    async def connect(endpoint, extra):
        bus = open_bus("zenoh", clock, mode="client", listen=[], connect=[endpoint], extra=extra,
                       connect_timeout_ms=1000)
        await bus.start()

    tls = session_config(tmp_path / "lab", Identity("watcher", LAB))
    names = "the host must also be one the router's certificate names"
    without = "A tls/ endpoint is a lab with security: give its security directory (--security DIR)"
    for endpoint, extra, hint in ((f"tls/127.0.0.1:{free_port()}", tls, names),
                                  (f"tls/127.0.0.1:{free_port()}", {}, without),  # no certificate of its own
                                  (f"tcp/127.0.0.1:{free_port()}", {}, None)):
        with pytest.raises(BusError) as said:
            clock.run(connect(endpoint, extra))
        assert f"nothing answered at {endpoint}" in str(said.value)
        for words in (names, without):
            assert (words in str(said.value)) == (words == hint), (words, str(said.value))


def test_a_second_security_init_of_a_directory_waits_for_the_first_and_signs_with_its_ca(tmp_path):
    """Two started together on a new directory (a provisioning script, a device each) each made a CA, and the first
    one's certificates were signed by a CA no longer on disk."""
    import fcntl

    from cryptography import x509

    from twin.tools.security_init import _init  # what init does once it holds the directory

    root = tmp_path / "lab"
    root.mkdir()
    with open(root / ".init.lock", "a+") as first:
        fcntl.flock(first, fcntl.LOCK_EX)  # as a first `twin security init` of the directory holds it
        second = subprocess.Popen([sys.executable, "-m", "twin", "security", "init", str(root), "--lab", LAB,
                                   "--device", "b"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  cwd=ROOT)
        try:
            assert second.stderr.readline() == f"waiting for another `twin security init` of {root} to finish\n"
            _init(root, LAB, ["a"], ["localhost", "127.0.0.1"], 365, "tls/127.0.0.1:7447")  # the first one's work
            assert second.poll() is None
        finally:
            fcntl.flock(first, fcntl.LOCK_UN)
    out, err = second.communicate(timeout=60)
    assert second.returncode == 0, err
    ca = x509.load_pem_x509_certificate((root / "ca.pem").read_bytes())
    for who in (Identity("device", LAB, "a"), Identity("device", LAB, "b"), Identity("router", LAB)):
        x509.load_pem_x509_certificate((who.folder(root) / "cert.pem").read_bytes()).verify_directly_issued_by(ca)
    assert json.loads((root / "labtwin-security.json").read_text())["devices"] == ["a", "b"]
