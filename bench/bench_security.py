"""Security benchmarks (issue [2 of 7]); prints tables.

    python bench/bench_security.py              # both sections (~2 minutes)
    python bench/bench_security.py forgery tls  # some sections

forgery: a live campaign through a `twin router` while a second process forges
results, faults, cancels and presence on every key it can reach; on a plain
loopback router and on a router with mutual TLS and the lab's access control.
tls: what TLS + access control cost on request/reply and on messages per second.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twin.campaign.journal_read import read_events  # noqa: E402
from bench.tables import free_port, table  # noqa: E402
from twin.core import keys  # noqa: E402
from twin.core.bus.security import Identity, session_config  # noqa: E402
from twin.core.messages import Kind, pack  # noqa: E402
from twin.runtime.lab import make_clock, prepare, run_async  # noqa: E402
from twin.tools.security_init import init  # noqa: E402

LAB = "bench"
DEVICES = ["synthesiser", "spectrometer-1", "spectrometer-2"]
MARK = 999.0  # the forged peak: an experiment that carries it took a forged result


def router(endpoint: str, security: Path | None) -> subprocess.Popen:
    args = [sys.executable, "-m", "twin", "router", "--listen", endpoint]
    if security is not None:
        args += ["--security", str(security)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    line = proc.stdout.readline().decode()
    assert line.startswith("router"), line + proc.stderr.read().decode()
    return proc


def session(endpoint: str, extra: dict | None = None) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("connect/timeout_ms", "3000")
    for path, value in (extra or {}).items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


# -- the attacker (a second process) -----------------------------------------------
def attack(endpoint: str, mode: str, security: str | None, seconds: float) -> None:
    """Forge on every key: ``blind`` guesses tokens, ``eavesdrop`` copies them from the commands it reads."""
    extra = session_config(security, Identity("device", LAB, "intruder")) if security else None
    try:
        s = session(endpoint, extra)
    except Exception as exc:  # noqa: BLE001 - a refused connection is a result here
        print(json.dumps({"connected": False, "why": str(exc)[:120]}), flush=True)
        return
    sent = {"results": 0, "faults": 0, "cancels": 0, "tokens": 0}
    n = [0]

    def forge(dev: str, task: str, attempt: int, token: str) -> None:
        def put(key: str, kind: Kind, body: dict, sender: str, tok: str) -> None:
            n[0] += 1
            s.put(key, pack(kind, body, id=f"forger:{n[0]}", sender=sender, t_lab=0.0, campaign="c1", task=task,
                            attempt=attempt, token=tok), congestion_control=zenoh.CongestionControl.BLOCK)

        result = {"outputs": {"peak_nm": MARK, "diameter_nm": 1.0}, "sample": {"kind": "qd", "peak_nm": MARK,
                                                                             "fwhm_nm": 1, "amplitude": 1}}
        other = next(d for d in DEVICES if d != dev)
        put(keys.evt(LAB, dev), Kind.RESULT, result, dev, token)  # the right key, sender and (copied or guessed) token
        put(keys.evt(LAB, dev), Kind.RESULT, result, dev, "")
        put(keys.evt(LAB, other), Kind.RESULT, result, dev, token)  # another device's key
        put(keys.evt(LAB, dev), Kind.RESULT, result, other, token)  # another sender
        put(keys.evt(LAB, dev), Kind.FAULT, {"code": "failed", "reason": "forged"}, dev, secrets.token_hex(16))
        put(keys.cmd(LAB, dev), Kind.CANCEL, {"reason": "forged"}, "orchestrator", secrets.token_hex(16))
        sent["results"] += 4
        sent["faults"] += 1
        sent["cancels"] += 1

    def on_cmd(sample: zenoh.Sample) -> None:
        env = json.loads(sample.payload.to_bytes())
        if env.get("kind") == "command":
            token = env.get("token", "") if mode == "eavesdrop" else secrets.token_hex(16)
            forge(keys.device_of(str(sample.key_expr)), env["task"], env["attempt"], token)

    sub = s.declare_subscriber(f"labtwin/{LAB}/dev/*/cmd", on_cmd)
    end = time.monotonic() + seconds
    stopped: list[int] = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(1))
    k = 0
    while time.monotonic() < end and not stopped:
        k += 1
        for dev in DEVICES:  # blind sprays too: tasks it guesses, presence it fakes
            forge(dev, f"e{k % 12}s{k % 2}", 1 + k % 2, secrets.token_hex(16))
        if k % 5 == 0:
            dev = DEVICES[k % len(DEVICES)]
            tok = s.liveliness().declare_token(keys.alive(LAB, dev))
            time.sleep(0.05)
            tok.undeclare()
            sent["tokens"] += 1
        time.sleep(0.1)
    sub.undeclare()
    s.close()
    print(json.dumps({"connected": True, **sent}), flush=True)


# -- the campaign under attack ------------------------------------------------------
def campaign(tmp: Path, endpoint: str, security: Path | None, mode: str | None, seed: int = 3) -> dict:
    raw = yaml.safe_load((ROOT / "scenarios" / "quantum_dots.yaml").read_text())
    raw.update(lab=LAB, name="forgery")
    raw["devices"]["synthesiser"]["instances"] = 1
    raw["devices"]["spectrometer"]["instances"] = 2
    for d in raw["devices"].values():
        d["faults"] = {}
    raw["campaign"].update(budget=12, max_in_flight=3, planner="random", seed=seed, stop_on_target=False)
    raw["clock"] = {"mode": "scaled", "speed": 3000.0}
    raw["bus"] = {"kind": "zenoh", "listen": [], "connect": [endpoint]}
    if security is not None:
        raw["bus"]["security"] = str(security)
    path = tmp / f"lab-{mode}-{security is not None}.yaml"
    path.write_text(yaml.safe_dump(raw))
    s = prepare(path)
    clock, db = make_clock(s), tmp / f"{path.stem}.db"
    attacker = None
    if mode is not None:
        attacker = subprocess.Popen([sys.executable, __file__, "--attacker", endpoint, mode,
                                     str(security) if security else "-", "30"],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
        time.sleep(1.5)  # its session is up before the campaign starts
    summary = clock.run(run_async(s, clock, db))
    sent = {}
    if attacker is not None:
        attacker.terminate()
        out, _ = attacker.communicate(timeout=30)
        lines = out.decode().strip().splitlines()
        sent = json.loads(lines[-1]) if lines else {"connected": "?"}
    done = [json.loads(e["detail"]) for e in read_events(db, "experiment.done")]
    forged_done = sum(1 for d in done if d["outputs"].get("peak_nm") == MARK or d["outputs"].get("diameter_nm") == 1.0)
    return {"summary": summary, "sent": sent, "forged_counted": forged_done,
            "rejected": len(read_events(db, "message.rejected")), "lost": len(read_events(db, "device.lost"))}


def forgery_section() -> None:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        init(tmp / "sec", LAB, [*DEVICES, "intruder"])
        for secure in (False, True):
            endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
            r = router(endpoint, tmp / "sec" if secure else None)
            try:
                for mode in (None, "blind", "eavesdrop"):
                    out = campaign(tmp, endpoint, tmp / "sec" if secure else None, mode)
                    s, sent = out["summary"], out["sent"]
                    forged = sum(sent.get(k, 0) for k in ("results", "faults", "cancels"))
                    rows.append(["mTLS + ACL" if secure else "plain loopback", mode or "none (baseline)",
                                 "yes" if sent.get("connected", True) else "no", forged, sent.get("tokens", 0),
                                 s.done, s.abandoned, s.failed_attempts, out["forged_counted"], out["rejected"],
                                 out["lost"], s.presence_flaps])
            finally:
                r.terminate()
                r.wait()
    table("Forgery: a second process forges on every key it can reach (quantum_dots, 12 experiments, seed 3)",
          ["bus", "attacker", "connected", "forged msgs", "fake presences", "done", "abandoned", "failed attempts",
           "forged results counted", "message.rejected", "device.lost", "flaps"], rows)


# -- TLS + ACL cost -------------------------------------------------------------------
def tls_section(n_rtt: int = 2000, n_msgs: int = 20000) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        init(tmp / "sec", LAB, ["synthesiser"])
        for secure in (False, True):
            endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
            r = router(endpoint, tmp / "sec" if secure else None)
            try:
                cfg = (lambda who: session_config(tmp / "sec", who)) if secure else (lambda who: None)
                orch = session(endpoint, cfg(Identity("orchestrator", LAB)))
                dev = session(endpoint, cfg(Identity("device", LAB, "synthesiser")))
                q = dev.declare_queryable(keys.health(LAB, "synthesiser"),
                                          lambda query: query.reply(query.key_expr, b"ok"))
                got = []
                sub = orch.declare_subscriber(keys.evt(LAB, "synthesiser"), lambda s: got.append(1))
                time.sleep(0.5)
                rtts = []
                for _ in range(n_rtt):
                    t0 = time.perf_counter()
                    replies = list(orch.get(keys.health(LAB, "synthesiser"), timeout=2.0))
                    rtts.append(time.perf_counter() - t0)
                    assert replies and replies[0].ok is not None
                payload = b"x" * 300
                t0 = time.perf_counter()
                for _ in range(n_msgs):
                    dev.put(keys.evt(LAB, "synthesiser"), payload, congestion_control=zenoh.CongestionControl.BLOCK)
                while len(got) < n_msgs and time.perf_counter() - t0 < 60:
                    time.sleep(0.005)
                rate = len(got) / (time.perf_counter() - t0)
                rtts.sort()
                rows.append(["mTLS + ACL" if secure else "plain tcp", f"{1e3 * statistics.median(rtts):.3f}",
                             f"{1e3 * rtts[int(0.99 * len(rtts))]:.3f}", f"{rate:,.0f}"])
                sub.undeclare()
                q.undeclare()
                for s in (orch, dev):
                    s.close()
            finally:
                r.terminate()
                r.wait()
    base_rtt, base_rate = float(rows[0][1]), float(rows[0][3].replace(",", ""))
    for row in rows:
        row += [f"{float(row[1]) / base_rtt:.2f}", f"{float(row[3].replace(',', '')) / base_rate:.2f}"]
    table(f"TLS + access control through a router on loopback ({n_rtt} request/replies, {n_msgs} messages of 300 B)",
          ["link", "request/reply p50 ms", "p99 ms", "messages/s", "p50 ÷ plain", "msgs/s ÷ plain"], rows)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--attacker"]:
        endpoint, mode, sec, seconds = sys.argv[2:6]
        attack(endpoint, mode, None if sec == "-" else sec, float(seconds))
        sys.exit(0)
    os.environ.setdefault("RUST_LOG", "error")
    wanted = set(sys.argv[1:]) or {"forgery", "tls"}
    if "forgery" in wanted:
        forgery_section()
    if "tls" in wanted:
        tls_section()
