"""One lab time across processes (issue [3 of 7]): how far a joined process's lab time is from the lab's.

    python bench/bench_labtime.py [--speed 3600] [--asks 200]

A lab process (this one: a router, the lab's clock published on it, one in-process device) and a
`twin device serve` process that follows the lab's clock. Each device is asked for its health, which carries
its lab time; the offset is its lab time minus the middle of the lab's before and after the answer, in wall
milliseconds. The in-process device shares the lab's clock, so its row is the measurement's own error
(half a round trip, at most); the other row is that plus the clocks' disagreement.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import free_port, table  # noqa: E402
from tests.conftest import qd_lab  # noqa: E402
from twin.core import keys  # noqa: E402
from twin.core.clock import LabClock  # noqa: E402
from twin.runtime.lab import build_actors, load_drivers, make_bus, make_clock, prepare  # noqa: E402
from twin.runtime.labtime import LabTimeSource  # noqa: E402


def _percentile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--speed", type=float, default=3600.0)
    ap.add_argument("--asks", type=int, default=200)
    args = ap.parse_args()
    router = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "lab.yaml"
        path.write_text(yaml.safe_dump(qd_lab(**{"clock": {"mode": "scaled", "speed": args.speed},
                                                  "bus": {"kind": "zenoh", "listen": [], "connect": [router]}})))
        s = prepare(path)
        procs = [subprocess.Popen([sys.executable, "-m", "twin", "router", "--listen", router],
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=ROOT)]
        procs[0].stdout.readline()
        procs.append(subprocess.Popen([sys.executable, "-m", "twin", "device", "serve", str(path), "--id",
                                       "spectrometer-2", "--connect", router],
                                      stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=ROOT))
        procs[1].stdout.readline()
        try:
            clock = make_clock(s)
            rows = clock.run(_measure(s, clock, args.asks))
        finally:
            for p in procs:
                p.terminate()
                p.wait()
    table(f"Lab time of a device vs the lab's, scaled clock at {args.speed:g}×, {args.asks} asks each "
          "(wall ms; loopback, 2 cores)",
          ["device", "offset p50", "offset p99", "offset max", "round trip p50", "p99 / in-process p99"], rows)


async def _measure(s, loop_clock: LabClock, asks: int) -> list[list]:
    bus = make_bus(s, loop_clock)
    await bus.start()
    source = LabTimeSource(bus, s.lab, loop_clock)
    source.start()
    actors = build_actors(s, load_drivers(s, only={"spectrometer-1"}), bus, loop_clock)
    for a in actors:
        await a.start()
    await loop_clock.sleep(1.0 * loop_clock.speed)  # the other process hears the clock
    out, base = [], None
    try:
        for name in ("spectrometer-1", "spectrometer-2"):
            offsets, trips = [], []
            for _ in range(asks):
                before = loop_clock.now()
                report = json.loads(await bus.request(keys.health(s.lab, name), b"", 5 * loop_clock.speed))
                after = loop_clock.now()
                offsets.append(abs(report["t_lab"] - (before + after) / 2) / loop_clock.speed * 1000)
                trips.append((after - before) / loop_clock.speed * 1000)
            p99 = _percentile(offsets, 0.99)
            base = base or p99
            where = "in the lab's process" if name == "spectrometer-1" else "another process, following"
            out.append([where, f"{statistics.median(offsets):.3f}", f"{p99:.3f}", f"{max(offsets):.3f}",
                        f"{statistics.median(trips):.3f}", f"{p99 / base:.2f}×"])
    finally:
        for a in actors:
            await a.stop()
        source.close()
        await bus.close()
    return out


if __name__ == "__main__":
    main()
