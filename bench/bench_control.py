"""Operator control over Zenoh (issue [7 of 7]): how long `twin ctl` acts take to take effect.

    python bench/bench_control.py [--pairs 50]

A live campaign (scaled clock, Zenoh on loopback) runs in another process; one operator session asks it for
its status (the baseline: a round trip that changes nothing) and pauses and resumes it ``--pairs`` times. A
pause's time is from the request to the answer, which is sent after the core has taken the pause (no dispatch
from then on) and the journal holds it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
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
from tests.conftest import qd_lab  # noqa: E402
from twin.core import keys  # noqa: E402
from twin.core.bus import open_bus  # noqa: E402
from twin.core.clock import LabClock  # noqa: E402


def _ms(xs: list[float], q: float) -> str:
    xs = sorted(xs)
    return f"{1000 * xs[min(len(xs) - 1, int(q * len(xs)))]:.1f}"


async def measure(endpoint: str, pairs: int) -> dict[str, list[float]]:
    host, port = endpoint.split("/")[1].split(":")
    deadline = time.monotonic() + 60
    while True:
        try:
            socket.create_connection((host, int(port)), timeout=1).close()
            break
        except OSError:
            if time.monotonic() > deadline:
                raise SystemExit(f"the campaign never listened at {endpoint}")
            await asyncio.sleep(0.05)
    bus = open_bus("zenoh", LabClock("wall"), mode="client", listen=[], connect=[endpoint])
    await bus.start()
    out: dict[str, list[float]] = {"status": [], "pause": [], "resume": []}
    try:
        while True:  # the campaign is up once it answers
            try:
                await bus.request(keys.control("t", "status"), b"{}", 1.0)
                break
            except Exception:
                await asyncio.sleep(0.05)
        for _ in range(pairs):
            for command in ("status", "pause", "resume"):
                t0 = time.perf_counter()
                answer = json.loads(await bus.request(keys.control("t", command), b'{"who": "bench"}', 5.0))
                out[command].append(time.perf_counter() - t0)
                assert answer["ok"], answer
    finally:
        await bus.close()
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=50)
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    d = scratch()
    lab = qd_lab(**{"campaign.budget": 100000, "campaign.max_in_flight": 3, "clock": {"mode": "scaled", "speed": 60},
                    "bus": {"kind": "zenoh", "listen": [endpoint]}})
    (d / "lab.yaml").write_text(yaml.safe_dump(lab))
    proc = subprocess.Popen([sys.executable, "-m", "twin", "run", str(d / "lab.yaml"), "--journal", str(d / "j.db"),
                             "--quiet"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        times = asyncio.run(measure(endpoint, args.pairs))
    finally:
        proc.kill()
        proc.wait()
    rows = [[f"{c}{' (baseline)' if c == 'status' else ''}", _ms(v, 0.5), _ms(v, 0.99), _ms(v, 1.0)]
            for c, v in times.items()]
    table(f"twin ctl over Zenoh on loopback: {args.pairs} requests each, wall ms from request to answer "
          "(a pause is answered once the core has taken it and the journal holds it)",
          ["request", "p50 ms", "p99 ms", "max ms"], rows)


if __name__ == "__main__":
    main()
