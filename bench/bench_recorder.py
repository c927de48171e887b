"""Recorder benchmarks for issue [2 of 5]: campaign speed with the Rerun recorder on vs off, recording size.

    python bench/bench_recorder.py [--pairs 15] [--sizes]

``--sizes`` adds the recording size of 1,000-experiment campaigns (minutes: GP-BO fits dominate).
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_kernel import STANDARD  # noqa: E402
from bench.tables import table  # noqa: E402
from twin.runtime.lab import prepare, run  # noqa: E402
from twin.view.watch import RecordOptions  # noqa: E402


def campaign(bus: str, record: bool) -> tuple[float, float, int]:
    """(CPU seconds, wall seconds until the recording is written, recording bytes) of one standard campaign. The
    wall time includes closing the recording (its last rows sent, the file written): what a user waits for."""
    s = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides=STANDARD)
    with tempfile.TemporaryDirectory() as d:
        rrd = Path(d) / "r.rrd"
        cpu0, wall0 = time.process_time(), time.perf_counter()
        run(s, journal=Path(d) / "j.db", bus=bus, record=RecordOptions(save=rrd) if record else None)
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        return cpu, wall, rrd.stat().st_size if record else 0


def interleaved(bus: str, pairs: int) -> tuple[list, list, int]:
    """(CPU s, wall s) off and on, alternating, so that load on the shared machine hits both alike."""
    off, on, size = [], [], 0
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=Path(tempfile.mkdtemp()) / "w.db", bus=bus,
        overrides={"campaign.budget": 5}, record=RecordOptions(save=Path(tempfile.mkdtemp()) / "w.rrd"))  # warm-up
    for _ in range(pairs):
        off.append(campaign(bus, False)[:2])
        cpu, wall, size = campaign(bus, True)
        on.append((cpu, wall))
    return off, on, size


def paired(off: list[float], on: list[float]) -> str:
    """The median of the pairs' ratios off ÷ on, with its interquartile range: the machine's load drifts
    between pairs more than within one, so pairs are compared, not medians of each side."""
    q = statistics.quantiles([a / b for a, b in zip(off, on)], n=4)
    return f"{q[1]:.2f} [{q[0]:.2f}–{q[2]:.2f}]"


def main() -> None:
    pairs = int(sys.argv[sys.argv.index("--pairs") + 1]) if "--pairs" in sys.argv else 15
    rows = []
    for bus in ("memory", "zenoh"):
        off, on, size = interleaved(bus, pairs)
        c_off, c_on = ([x[0] for x in v] for v in (off, on))
        w_off, w_on = ([x[1] for x in v] for v in (off, on))
        rows.append([f"{bus}, off", f"{statistics.median(w_off):.2f}", "1.00", "1.00",
                     f"{statistics.median(c_off):.2f}", "1.00", ""])
        rows.append([f"{bus}, --save", f"{statistics.median(w_on):.2f}", paired(w_off, w_on),
                     f"{statistics.median(w_off) / statistics.median(w_on):.2f}", f"{statistics.median(c_on):.2f}",
                     paired(c_off, c_on), f"{size / 2**20:.1f}"])
    table(f"Campaign speed with the Rerun recorder: flaky_lab without crashes, 400 experiments, {pairs} "
          "interleaved pairs; wall s (until the recording is written) and CPU s (Rerun's threads included) are "
          "medians, 'speed' and 'CPU' the median of each pair's off ÷ on [IQR], 'medians' the off median ÷ the on "
          "median",
          ["run", "wall s", "speed", "medians", "CPU s", "CPU", "MB"], rows)
    if "--sizes" not in sys.argv:
        return
    sizes = []
    for scenario in ("quantum_dots", "flaky_lab"):
        with tempfile.TemporaryDirectory() as d:
            rrd = Path(d) / "r.rrd"
            summ = run(ROOT / "scenarios" / f"{scenario}.yaml", journal=Path(d) / "j.db", bus="memory",
                       overrides={"campaign.budget": 1000, "campaign.stop_on_target": False},
                       record=RecordOptions(save=rrd))
            mb = rrd.stat().st_size / 2**20
            jmb = (Path(d) / "j.db").stat().st_size / 2**20
        sizes.append([scenario, summ.done, f"{mb:.1f}", f"{jmb:.1f}", f"{mb / jmb:.2f}"])
    table("Recording size per 1,000 experiments (memory bus)",
          ["scenario", "experiments", "recording MB", "journal MB", "÷ journal"], sizes)


if __name__ == "__main__":
    main()
