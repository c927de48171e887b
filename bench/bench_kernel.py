"""Kernel benchmarks (issues [1 of 5] and [1 of 7]); prints tables, ratios against baselines run alongside.

    python bench/bench_kernel.py            # everything (a few minutes)
    python bench/bench_kernel.py speed env  # some sections: speed, env, bus, detect, scale, resume
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import simpy_lab  # noqa: E402
from bench.scratch import scratch  # noqa: E402
from bench.tables import free_port, table  # noqa: E402
from twin.core.bus.zenoh_bus import ZenohBus  # noqa: E402
from twin.core.bus.zenoh_config import ZenohOptions  # noqa: E402
from twin.core.clock import LabClock  # noqa: E402
from twin.runtime.lab import prepare, run  # noqa: E402


# -- 1. virtual-time speed of the standard campaign vs SimPy ---------------
STANDARD = {"campaign.budget": 400, "campaign.stop_on_target": False,
            "devices.synthesiser.faults.mtbc_h": 0, "devices.reactor.faults.mtbc_h": 0,
            "devices.spectrometer.faults.mtbc_h": 0}


def best_of(n: int, fn) -> tuple[float, object]:
    """The fastest of ``n`` timings (a single short timing swings with the machine's load)."""
    best, out = float("inf"), None
    for _ in range(n):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def machines_only(s):
    """The same lab with physics-free drivers: every step just sleeps its drawn duration."""
    bare = s.model_copy(deep=True)
    for spec in bare.devices.values():
        spec.driver = "machine"
        spec.steps = ["op"]
        spec.options = {}  # the physics drivers' options (the reactor's telemetry_s): the machine takes none
    return bare.model_copy(update={"workflow": [w.model_copy(update={"step": "op"}) for w in bare.workflow]})


def bench_speed() -> None:
    s = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides=STANDARD, bus="memory")
    bare = machines_only(s)
    d = scratch()
    run(s, journal=d / "warm.db", overrides={"campaign.budget": 2})  # imports are paid once, not timed
    n = s.campaign.budget

    def twin(lab, runtime, bus="memory"):
        return lambda: run(lab, journal=d / "j.db", runtime=runtime, bus=bus)

    simpy_bare, _ = best_of(7, lambda: simpy_lab.run(s))
    simpy_phys, _ = best_of(3, lambda: simpy_lab.run(s, physics=True))
    fast, summ = best_of(3, twin(s, "fast"))
    fast_bare, _ = best_of(3, twin(bare, "fast"))
    live, _ = best_of(3, twin(s, "asyncio"))
    zenoh_t, _ = best_of(2, twin(s, "asyncio", "zenoh"))
    us = lambda t: f"{1e6 * t / n:,.0f}"  # noqa: E731
    table(f"Virtual-time speed, the standard campaign (flaky_lab, {n} experiments, {summ.done} done; best of several "
          "runs; µs per experiment)",
          ["what", "µs/exp", "ratio", "is", "target"],
          [["SimPy, bare skeleton (baseline A)", us(simpy_bare), "", "", ""],
           ["SimPy + the drivers' physics (baseline B)", us(simpy_phys), "", "", ""],
           ["fast runtime", us(fast), f"{simpy_phys / fast:.2f}", "fast ÷ B", "≥ 1.0"],
           ["fast runtime, machine drivers (no physics)", us(fast_bare), f"{simpy_bare / fast_bare:.3f}",
            "physics-free ÷ A", "≥ 0.5"],
           ["asyncio runtime, memory bus", us(live), f"{fast / live:.2f}", "asyncio ÷ fast", ""],
           ["asyncio runtime, Zenoh bus", us(zenoh_t), f"{live / zenoh_t:.2f}", "Zenoh ÷ memory", "≥ 0.5"]])


# -- 1b. the learning environments ---------------------------------------------
def bench_env(seconds: float = 4.0) -> None:
    import numpy as np

    from agents.scheduling_env import SchedulingEnv

    rows = []
    for name in ("jobshop", "flaky_lab"):
        env = SchedulingEnv(prepare(ROOT / "scenarios" / f"{name}.yaml"), randomise=False, encoding="slots")
        rng = np.random.default_rng(0)
        env.reset(seed=0)
        steps = resets = 0
        reset_s, t0 = 0.0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            _, _, term, trunc, _ = env.step(rng.choice(np.flatnonzero(env.action_masks())))
            steps += 1
            if term or trunc:
                t1 = time.perf_counter()
                env.reset(seed=resets + 1)
                reset_s += time.perf_counter() - t1
                resets += 1
        wall = time.perf_counter() - t0
        rows.append([f"labtwin/Scheduling-v0, {name}", f"{steps / wall:,.0f}", "≥ 20,000" if name == "jobshop" else "≥ 5,000",
                     f"{1000 * reset_s / max(resets, 1):.2f}", "≤ 1"])
    rows.append(["MaskablePPO on flaky_lab, the trainer's settings", f"{_ppo_steps_per_s():,.0f}", "≥ 2,000", "", ""])
    table("Learning environments: random valid actions (steps/s) and resets (ms)",
          ["what", "steps/s", "target", "reset ms", "target"], rows)


def _ppo_steps_per_s(steps: int = 4096) -> float:
    import torch
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.scheduling_env import SchedulingEnv
    from agents.sb3_logging import without_log_dir
    from agents.train_scheduler import PPO_SETTINGS

    torch.set_num_threads(1)
    s = prepare(ROOT / "scenarios" / "flaky_lab.yaml")
    venv = DummyVecEnv([lambda: SchedulingEnv(s, encoding="slots") for _ in range(2)])
    model = without_log_dir(MaskablePPO("MlpPolicy", venv, seed=0, verbose=0, **PPO_SETTINGS))
    model.learn(1024)  # warm up
    t0 = time.perf_counter()
    model.learn(steps)
    return steps / (time.perf_counter() - t0)


# -- 2. Zenoh bus: delivery into asyncio, request/reply -------------------
N_MESSAGES = 200_000


def _publisher(endpoint: str, n: int, received: threading.Event) -> None:
    cfg = ZenohOptions(listen=[], connect=[endpoint]).config()
    with zenoh.open(cfg) as s:
        pub = s.declare_publisher("bench/tp", congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.5)  # let the subscriber's declaration reach this session
        for i in range(n):
            pub.put(i.to_bytes(4, "little"))
        received.wait(120)  # closing a session drops what it has not sent yet


async def _throughput(batched: bool) -> float:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    loop = asyncio.get_running_loop()
    got = [0]
    finished = asyncio.Event()
    t_first = [0.0]

    def handler(key, payload):
        if got[0] == 0:
            t_first[0] = time.perf_counter()
        got[0] += 1
        if got[0] == N_MESSAGES:
            finished.set()

    if batched:
        bus = ZenohBus(LabClock("wall"), ZenohOptions(listen=[endpoint]))
        await bus.start()
        bus.subscribe("bench/tp", handler)
        session = None
    else:
        session = zenoh.open(ZenohOptions(listen=[endpoint]).config())
        session.declare_subscriber("bench/tp", lambda smp: loop.call_soon_threadsafe(
            handler, str(smp.key_expr), smp.payload.to_bytes()))
    received = threading.Event()
    th = threading.Thread(target=_publisher, args=(endpoint, N_MESSAGES, received), daemon=True)
    th.start()
    await asyncio.wait_for(finished.wait(), 120)
    elapsed = time.perf_counter() - t_first[0]
    received.set()
    th.join()
    if batched:
        await bus.close()
    else:
        session.close()
    return N_MESSAGES / elapsed


async def _request_reply(n: int = 3000) -> list[float]:
    port = free_port()
    clock = LabClock("wall")
    server = ZenohBus(clock, ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"]))
    client = ZenohBus(clock, ZenohOptions(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    await server.start()
    await client.start()

    async def echo(key, payload):
        return payload

    server.serve("bench/echo", echo)
    await asyncio.sleep(0.5)
    for _ in range(200):  # warm up
        await client.request("bench/echo", b"x", timeout=5)
    lat = []
    for _ in range(n):
        t = time.perf_counter()
        await client.request("bench/echo", b"x", timeout=5)
        lat.append((time.perf_counter() - t) * 1000)
    await client.close()
    await server.close()
    return sorted(lat)


def _raw_get_latency(n: int = 3000) -> list[float]:
    """Baseline: zenoh-python's own blocking get against a callback queryable, no asyncio."""
    port = free_port()
    a = zenoh.open(ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"]).config())
    b = zenoh.open(ZenohOptions(listen=[], connect=[f"tcp/127.0.0.1:{port}"]).config())

    def echo(query):
        with query:
            query.reply(query.key_expr, query.payload.to_bytes())

    a.declare_queryable("bench/raw", echo)
    time.sleep(0.5)
    lat = []
    for i in range(n + 200):
        t = time.perf_counter()
        for _ in b.get("bench/raw", payload=b"x"):
            pass
        if i >= 200:
            lat.append((time.perf_counter() - t) * 1000)
    b.close()
    a.close()
    return sorted(lat)


def bench_bus() -> None:
    naive = asyncio.run(_throughput(batched=False))
    batched = asyncio.run(_throughput(batched=True))
    lat = asyncio.run(_request_reply())
    raw = _raw_get_latency()
    p50, p99 = lat[len(lat) // 2], lat[int(len(lat) * 0.99)]
    r50, r99 = raw[len(raw) // 2], raw[int(len(raw) * 0.99)]
    table(f"Zenoh bus over loopback, two sessions ({N_MESSAGES:,} messages of 4 bytes; 3,000 requests)",
          ["measure", "value", "÷ baseline"],
          [["delivered into asyncio, naive call_soon_threadsafe per message (baseline)", f"{naive:,.0f} msg/s", "1.00"],
           ["delivered into asyncio, ZenohBus batched hand-off", f"{batched:,.0f} msg/s", f"{batched / naive:.2f}"],
           ["request/reply p50, raw zenoh-python blocking get (baseline)", f"{r50:.3f} ms", "1.00"],
           ["request/reply p50, ZenohBus.request from asyncio", f"{p50:.3f} ms", f"{p50 / r50:.2f}"],
           ["request/reply p99, raw zenoh-python blocking get (baseline)", f"{r99:.3f} ms", "1.00"],
           ["request/reply p99, ZenohBus.request from asyncio", f"{p99:.3f} ms", f"{p99 / r99:.2f}"]])


# -- 3. detecting a killed and a hung device -------------------------------
CHILD = """
import sys, time, zenoh, json
cfg = zenoh.Config()
cfg.insert_json5("mode", '"peer"'); cfg.insert_json5("scouting/multicast/enabled", "false")
cfg.insert_json5("listen/endpoints", "[]"); cfg.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
cfg.insert_json5("transport/link/tx/lease", "1000"); cfg.insert_json5("transport/link/tx/keep_alive", "4")
s = zenoh.open(cfg)
tok = s.liveliness().declare_token("bench/alive/dev")
print("ready", flush=True)
time.sleep(3600)
"""


async def _detect(sig: int) -> float:
    port = free_port()
    bus = ZenohBus(LabClock("wall"), ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"], lease_ms=1000))
    await bus.start()
    seen = {}
    alive = asyncio.Event()
    gone = asyncio.Event()

    def on_change(key, is_alive):
        if is_alive:
            alive.set()
        else:
            seen["t"] = time.perf_counter()
            gone.set()

    bus.watch_tokens("bench/alive/*", on_change)
    child = subprocess.Popen([sys.executable, "-c", CHILD, f"tcp/127.0.0.1:{port}"], stdout=subprocess.PIPE)
    child.stdout.readline()
    await asyncio.wait_for(alive.wait(), 10)
    await asyncio.sleep(0.3)
    t0 = time.perf_counter()
    os.kill(child.pid, sig)
    await asyncio.wait_for(gone.wait(), 10)
    child.kill()
    child.wait()
    await bus.close()
    return (seen["t"] - t0) * 1000


def bench_detect() -> None:
    killed = [asyncio.run(_detect(signal.SIGKILL)) for _ in range(5)]
    hung = [asyncio.run(_detect(signal.SIGSTOP)) for _ in range(3)]
    table("Detecting device loss through liveliness (link lease 1000 ms), wall milliseconds",
          ["device", "runs", "median ms", "max ms", "target"],
          [["killed (SIGKILL)", len(killed), f"{statistics.median(killed):.1f}", f"{max(killed):.1f}", "≤ 50"],
           ["hung (SIGSTOP)", len(hung), f"{statistics.median(hung):.0f}", f"{max(hung):.0f}", "≤ 1500"]])


# -- 4. memory and time of long campaigns ----------------------------------
SCALE_CHILD = """
import json, resource, sys, tempfile, time
from pathlib import Path
from twin import run
n = int(sys.argv[1])
with tempfile.TemporaryDirectory() as d:
    s = run("scenarios/quantum_dots.yaml", journal=Path(d) / "j.db", bus="memory",
            overrides={"campaign.budget": n, "campaign.stop_on_target": False, "campaign.planner": "random"})
    size = (Path(d) / "j.db").stat().st_size
print(json.dumps({"n": n, "wall": s.wall_s, "done": s.done, "lab_h": s.lab_hours,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "db_mb": size / 2**20}))
"""


def bench_scale() -> None:
    rows = []
    for n in (1000, 5000, 10000):
        out = subprocess.run([sys.executable, "-c", SCALE_CHILD, str(n)], capture_output=True, text=True,
                             cwd=ROOT, check=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        rows.append([n, r["done"], f"{r['lab_h']:.0f}", f"{r['wall']:.1f}", f"{1000 * r['wall'] / n:.2f}",
                     f"{r['rss_mb']:.0f}", f"{r['db_mb']:.0f}"])
    table("Long virtual campaigns (quantum_dots, memory bus): time and memory should grow linearly",
          ["experiments", "done", "lab-h", "wall s", "ms per experiment", "peak RSS MB", "journal MB"], rows)
    slope = (float(rows[-1][5]) - float(rows[0][5])) * 2**20 / (int(rows[-1][0]) - int(rows[0][0]))
    print(f"retained per experiment (peak RSS slope, 1k → 10k): {slope / 1024:.2f} KB (target ≤ 2 KB)")


# -- 5. kill and resume -----------------------------------------------------------------
def _killed_at(s, db, row):
    from twin.campaign.journal import Journal

    Journal.FLUSH_EVERY = 25
    append = Journal._append

    def dying(self, *r):
        if self._seq + 1 == row:
            os.kill(os.getpid(), signal.SIGKILL)
        append(self, *r)

    Journal._append = dying
    run(s, journal=db)


def bench_resume(cycles: int = 100) -> None:
    import multiprocessing
    import random
    import sqlite3

    from twin.runtime.resume import resume

    def tables(db):
        with sqlite3.connect(db) as c:
            return (c.execute("SELECT * FROM events ORDER BY seq").fetchall(),
                    c.execute("SELECT * FROM experiments ORDER BY id").fetchall())

    rng, d = random.Random(0), scratch()
    labs = {name: prepare(ROOT / "scenarios" / f"{name}.yaml", bus="memory", overrides={"campaign.budget": 30})
            for name in ("flaky_lab", "quantum_dots")}
    whole = {}
    for name, s in labs.items():
        run(s, journal=d / f"{name}.db")
        whole[name] = tables(d / f"{name}.db")
    lost = duplicated = diverged = 0
    t0 = time.perf_counter()
    for i in range(cycles):
        name = rng.choice(sorted(labs))
        db = d / f"k{i}.db"
        child = multiprocessing.get_context("fork").Process(
            target=_killed_at, args=(labs[name], db, rng.randint(1, len(whole[name][0]))))
        child.start()
        child.join()
        resume(db)
        events, exps = tables(db)
        finals = [r[3] for r in events if r[2] in ("experiment.done", "experiment.abandoned")]
        duplicated += len(finals) - len(set(finals))
        lost += len({r[0] for r in whole[name][1]} - {r[0] for r in exps})
        diverged += (events, exps) != whole[name]
    table(f"Kill (SIGKILL at a random journal event) and resume, {cycles} cycles over flaky_lab and quantum_dots "
          f"({time.perf_counter() - t0:.0f} s)",
          ["cycles", "lost", "duplicated", "diverged", "target"], [[cycles, lost, duplicated, diverged, "0 / 0 / 0"]])


SECTIONS = {"speed": bench_speed, "env": bench_env, "bus": bench_bus, "detect": bench_detect, "scale": bench_scale,
            "resume": bench_resume}

if __name__ == "__main__":
    for name in sys.argv[1:] or list(SECTIONS):
        SECTIONS[name]()
