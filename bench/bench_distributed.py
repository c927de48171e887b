"""A lab spread over processes (issue [5 of 5]): through a `twin router` against direct links, and MQTT vs Zenoh.

    python bench/bench_distributed.py        # about a minute; needs mosquitto installed

Every number crosses OS processes on loopback. Baselines run in the same
invocation: direct peer-to-peer links for the router, a native Zenoh device
for the MQTT adapter.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.scratch import scratch  # noqa: E402
from bench.tables import free_port, table  # noqa: E402
from twin.core import keys  # noqa: E402
from twin.core.bus.zenoh_bus import ZenohBus  # noqa: E402
from twin.core.bus.zenoh_config import ZenohOptions  # noqa: E402
from twin.core.clock import LabClock  # noqa: E402
from twin.core.messages import Kind, decode, pack  # noqa: E402
from twin.runtime.labtime import LabTimeSource  # noqa: E402

N_REQUESTS, N_MESSAGES, N_STEPS = 2000, 50_000, 300

SERVER = """
import asyncio, sys
from twin.core.bus.zenoh_bus import ZenohBus
from twin.core.bus.zenoh_config import ZenohOptions
from twin.core.clock import LabClock
async def main():
    listen, connect = sys.argv[1].split(",") if sys.argv[1] else [], sys.argv[2].split(",") if sys.argv[2] else []
    bus = ZenohBus(LabClock("wall"), ZenohOptions(listen=listen, connect=connect))
    await bus.start()
    async def echo(key, payload):
        return payload
    bus.serve("bench/echo", echo)
    token = bus.declare_token("bench/alive/dev")
    print("ready", flush=True)
    if sys.argv[3] == "publish":
        await asyncio.sleep(1.0)
        for i in range(int(sys.argv[4])):
            bus.publish("bench/tp", i.to_bytes(4, "little"))
            if i % 1000 == 0:
                await asyncio.sleep(0)
    await asyncio.Event().wait()
LabClock("wall").run(main())
"""


def child(listen: str, connect: str, mode: str = "serve", n: int = 0) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", SERVER, listen, connect, mode, str(n)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.readline().decode().startswith("ready"), proc.stderr.read().decode()
    return proc


def stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGCONT)  # a frozen process cannot die
        p.kill()
        p.wait()


async def measure_link(topology: str, router: str | None) -> dict[str, float]:
    """Request/reply, throughput and loss detection between this process and a child, ``direct`` or via ``router``."""
    out = {}
    if topology == "direct":
        port = free_port()
        mine, theirs = ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"]), (lambda: ("", f"tcp/127.0.0.1:{port}"))
    else:
        mine, theirs = ZenohOptions(listen=[], connect=[router]), (lambda: ("", router))
    bus = ZenohBus(LabClock("wall"), mine)
    await bus.start()
    try:
        # request/reply
        server = child(*theirs())
        await asyncio.sleep(0.5)
        for _ in range(200):
            await bus.request("bench/echo", b"x", timeout=5)
        lat = []
        for _ in range(N_REQUESTS):
            t = time.perf_counter()
            await bus.request("bench/echo", b"x", timeout=5)
            lat.append((time.perf_counter() - t) * 1000)
        lat.sort()
        out["p50"], out["p99"] = lat[len(lat) // 2], lat[int(len(lat) * 0.99)]
        # loss detection: kill the server, then freeze a fresh one
        for sig, name in ((signal.SIGKILL, "kill"), (signal.SIGSTOP, "freeze")):
            proc = server if name == "kill" else child(*theirs())
            present, gone, t = asyncio.Event(), asyncio.Event(), {}

            def seen(key, alive, present=present, gone=gone, t=t):
                if alive:
                    present.set()
                else:
                    t.setdefault("gone", time.perf_counter())
                    gone.set()

            watcher = bus.watch_tokens("bench/alive/*", seen)
            await asyncio.wait_for(present.wait(), 10)
            await asyncio.sleep(0.3)
            t0 = time.perf_counter()
            os.kill(proc.pid, sig)
            await asyncio.wait_for(gone.wait(), 10)
            out[name] = (t["gone"] - t0) * 1000
            watcher.close()
            stop(proc)
        # throughput
        got, done = [0], asyncio.Event()
        first = [0.0]

        def count(key, payload):
            if got[0] == 0:
                first[0] = time.perf_counter()
            got[0] += 1
            if got[0] == N_MESSAGES:
                done.set()

        bus.subscribe("bench/tp", count)
        publisher = child(*theirs(), "publish", N_MESSAGES)
        await asyncio.wait_for(done.wait(), 120)
        out["msg_s"] = N_MESSAGES / (time.perf_counter() - first[0])
        stop(publisher)
    finally:
        await bus.close()
    return out


def mosquitto() -> tuple[subprocess.Popen, str]:
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = free_port()
    conf = scratch() / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nset_tcp_nodelay true\n")
    proc = subprocess.Popen([binary, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(100):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return proc, f"127.0.0.1:{port}"
        except OSError:
            time.sleep(0.05)
    raise RuntimeError("mosquitto did not start")


async def round_trips(bus: ZenohBus, lab: str, device: str, step: str, n: int) -> list[float]:
    """Command → result over the bus to ``device`` (a device actor in another process), wall ms."""
    results: dict[str, asyncio.Future] = {}

    def on_event(key, payload):
        env, body = decode(payload)
        fut = results.get(env.task)
        if fut is not None and env.kind in (Kind.RESULT, Kind.FAULT, Kind.REJECTED) and not fut.done():
            fut.set_result((env.kind, body))

    sub = bus.subscribe(keys.evt(lab, device), on_event)
    ids, lat = itertools.count(), []
    loop = asyncio.get_running_loop()
    for i in range(n + 30):
        task = f"t{next(ids)}"
        results[task] = loop.create_future()
        body = {"step": step, "params": {}, "sample": {"peak_nm": 520.0, "kind": "qd"}, "expected_s": 1.0}
        t = time.perf_counter()
        bus.publish(keys.cmd(lab, device), pack(Kind.COMMAND, body, id=f"bench:{task}", sender="bench", t_lab=0.0,
                                                campaign="bench", task=task, attempt=1))
        kind, body = await asyncio.wait_for(results[task], 10)
        assert kind == Kind.RESULT, f"{device} answered {kind}: {body}"
        if i >= 30:
            lat.append((time.perf_counter() - t) * 1000)
    sub.close()
    return sorted(lat)


async def mqtt_vs_native(router: str, broker: str) -> dict[str, list[float]]:
    lab = {"name": "bench", "lab": "bench",
           "devices": {"m": {"driver": "machine", "steps": ["op"], "duration": {"mean_s": 0, "cv": 0}},
                       "reader": {"driver": "mqtt", "steps": ["measure"], "duration": {"mean_s": 0, "cv": 0},
                                  "options": {"broker": broker, "topic": "bench/reader", "steps": ["measure"]}}},
           "workflow": [{"step": "op", "device": "m"}, {"step": "measure", "device": "reader"}]}
    path = scratch() / "lab.yaml"
    path.write_text(yaml.safe_dump(lab))
    instrument = subprocess.Popen([sys.executable, "examples/mqtt_instrument.py", "--broker", broker, "--topic",
                                   "bench/reader", "--seconds", "0"], cwd=ROOT, stdout=subprocess.PIPE)
    instrument.stdout.readline()
    serve = [subprocess.Popen([sys.executable, "-m", "twin", "device", "serve", str(path), "--id", name, "--connect",
                               router, "--clock", "wall"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for name in ("m", "reader")]
    for p in serve:
        p.stdout.readline()
    clock = LabClock("wall")
    bus = ZenohBus(clock, ZenohOptions(listen=[], connect=[router]))
    await bus.start()
    lab_time = LabTimeSource(bus, "bench", clock)  # the devices take commands once they have the lab's time
    lab_time.start()
    try:
        await asyncio.sleep(1.0)
        return {"native": await round_trips(bus, "bench", "m", "op", N_STEPS),
                "mqtt": await round_trips(bus, "bench", "reader", "measure", N_STEPS)}
    finally:
        lab_time.close()
        await bus.close()
        stop(instrument, *serve)


def main() -> None:
    port = free_port()
    router_addr = f"tcp/127.0.0.1:{port}"
    router = subprocess.Popen([sys.executable, "-m", "twin", "router", "--listen", router_addr], cwd=ROOT,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    router.stdout.readline()
    broker = None
    try:
        direct = asyncio.run(measure_link("direct", None))
        routed = asyncio.run(measure_link("router", router_addr))
        rows = [[what, f"{direct[k]:{fmt}}", f"{routed[k]:{fmt}}", f"{routed[k] / direct[k]:.2f}"]
                for what, k, fmt in (("request/reply p50 (ms)", "p50", ".3f"), ("request/reply p99 (ms)", "p99", ".3f"),
                                     ("messages per second", "msg_s", ",.0f"), ("kill seen after (ms)", "kill", ".1f"),
                                     ("freeze seen after (ms, lease 1000)", "freeze", ".0f"))]
        table("Two processes on loopback: direct peer link (baseline) vs through `twin router`",
              ["measure", "direct", "via router", "÷ direct"], rows)
        broker_proc, broker = mosquitto()
        trips = asyncio.run(mqtt_vs_native(router_addr, broker))
        n50, n99 = trips["native"][len(trips["native"]) // 2], trips["native"][int(N_STEPS * 0.99)]
        m50, m99 = trips["mqtt"][len(trips["mqtt"]) // 2], trips["mqtt"][int(N_STEPS * 0.99)]
        table(f"A step's round trip (command → result, {N_STEPS} steps, zero-length), devices in their own processes "
              "through the router",
              ["device", "p50 ms", "p99 ms", "p50 ÷ native"],
              [["native Zenoh device (machine driver; baseline)", f"{n50:.2f}", f"{n99:.2f}", "1.00"],
               ["MQTT instrument via the adapter and mosquitto", f"{m50:.2f}", f"{m99:.2f}", f"{m50 / n50:.2f}"]])
        stop(broker_proc)
    finally:
        stop(router)


if __name__ == "__main__":
    main()
