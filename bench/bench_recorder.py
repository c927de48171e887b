"""Recorder benchmarks for issue [2 of 5]: campaign speed with the Rerun recorder on vs off, recording size.

    python bench/bench_recorder.py [--pairs 15] [--sizes] [--isolated]

``--sizes`` adds the recording size of 1,000-experiment campaigns (minutes: GP-BO fits dominate).
``--isolated`` gives instead the recorder's own cost: what one campaign handed its observer, handed again to a new
observer and recording, the campaign not running (process CPU, Rerun's threads included; best of 15).
"""

from __future__ import annotations

import gc
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_kernel import STANDARD  # noqa: E402
from bench.scratch import scratch  # noqa: E402
from bench.tables import table  # noqa: E402
from twin.runtime.lab import prepare, run  # noqa: E402
from twin.view.observer import LabObserver  # noqa: E402
from twin.view.recorder import open_recording  # noqa: E402
from twin.view.watch import RecordOptions  # noqa: E402


def campaign(bus: str, record: bool) -> tuple[float, float, int]:
    """(CPU seconds, wall seconds until the recording is written, recording bytes) of one standard campaign. The
    wall time includes closing the recording (its last rows sent, the file written): what a user waits for.

    The garbage of the campaigns before is collected first, outside the timing, so that each starts as the one
    campaign of a `twin run` process does. Left to the collector, the previous campaigns' state (~10,000 objects
    each, freed only by a full collection) made one full pass over the process (~120,000 objects once Rerun is
    imported; 60-200 ms here) every three or four pairs, and it fell in recorded campaigns (4 of 10) rather than
    unrecorded ones (0 of 10): they make more young objects, so they cross the collector's threshold."""
    s = prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides=STANDARD)
    with tempfile.TemporaryDirectory() as d:
        rrd = Path(d) / "r.rrd"
        gc.collect()
        cpu0, wall0 = time.process_time(), time.perf_counter()
        run(s, journal=Path(d) / "j.db", bus=bus, record=RecordOptions(save=rrd) if record else None)
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        return cpu, wall, rrd.stat().st_size if record else 0


def interleaved(bus: str, pairs: int) -> tuple[list, list, int]:
    """(CPU s, wall s) off and on, alternating, so that load on the shared machine hits both alike."""
    off, on, size = [], [], 0
    run(ROOT / "scenarios" / "quantum_dots.yaml", journal=scratch() / "w.db", bus=bus,
        overrides={"campaign.budget": 5}, record=RecordOptions(save=scratch() / "w.rrd"))  # warm-up
    for _ in range(pairs):
        off.append(campaign(bus, False)[:2])
        cpu, wall, size = campaign(bus, True)
        on.append((cpu, wall))
    return off, on, size


def paired(off: list[float], on: list[float]) -> str:
    """The median of the pairs' ratios off ÷ on, with its interquartile range: the machine's load drifts
    between pairs more than within one, so pairs are compared, not medians of each side."""
    q = statistics.quantiles([a / b for a, b in zip(off, on)], n=4)
    return f"{q[1]:.3f} [{q[0]:.3f}–{q[2]:.3f}]"


def longer(off: list[float], on: list[float]) -> str:
    """How much longer a recorded campaign takes, %: the median of the pairs' on ÷ off − 1 [IQR], and the on
    median ÷ the off median − 1 (the issue's "overhead": the extra time)."""
    q = statistics.quantiles([100 * (b / a - 1) for a, b in zip(off, on)], n=4)
    return f"{q[1]:.1f} [{q[0]:.1f}–{q[2]:.1f}]; {100 * (statistics.median(on) / statistics.median(off) - 1):.1f}"


def main() -> None:
    pairs = int(sys.argv[sys.argv.index("--pairs") + 1]) if "--pairs" in sys.argv else 15
    rows = []
    for bus in ("memory", "zenoh"):
        off, on, size = interleaved(bus, pairs)
        c_off, c_on = ([x[0] for x in v] for v in (off, on))
        w_off, w_on = ([x[1] for x in v] for v in (off, on))
        rows.append([f"{bus}, off", f"{statistics.median(w_off):.3f}", "1", "1", "0",
                     f"{statistics.median(c_off):.3f}", "1", ""])
        rows.append([f"{bus}, --save", f"{statistics.median(w_on):.3f}", paired(w_off, w_on),
                     f"{statistics.median(w_off) / statistics.median(w_on):.3f}", longer(w_off, w_on),
                     f"{statistics.median(c_on):.3f}", paired(c_off, c_on), f"{size / 2**20:.1f}"])
    table(f"Campaign speed with the Rerun recorder: flaky_lab without crashes, 400 experiments, {pairs} "
          "interleaved pairs; wall s (until the recording is written) and CPU s (Rerun's threads included) are "
          "medians, 'speed' and 'CPU' the median of each pair's off ÷ on [IQR], 'medians' the off median ÷ the on "
          "median, 'longer %' the median of each pair's on ÷ off − 1 [IQR]; the on median ÷ the off median − 1",
          ["run", "wall s", "speed", "medians", "longer %", "CPU s", "CPU", "MB"], rows)
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


class _Taped(LabObserver):
    """An observer that also keeps what it is handed, to hand it again."""

    def __init__(self, canvas: Any) -> None:
        super().__init__(canvas)
        self.tape: list[tuple[str, Any]] = []

    def on_note(self, n: Any) -> None:
        self.tape.append(("note", n))
        super().on_note(n)

    def on_envelope(self, env: dict) -> None:
        self.tape.append(("envelope", env))
        super().on_envelope(env)


class _Blank:
    """A canvas that draws nothing: the observer's own work."""

    def _nothing(self, *args: Any, **kwargs: Any) -> None:
        return None

    scalar = scalars = state = text = line = curve = points = document = image = flush = _nothing


def isolated(repeats: int = 15) -> None:
    with tempfile.TemporaryDirectory() as d:
        recording = open_recording("tape", save=Path(d) / "tape.rrd")
        taped = _Taped(recording.canvas)
        run(prepare(ROOT / "scenarios" / "flaky_lab.yaml", overrides=STANDARD), journal=Path(d) / "j.db",
            bus="memory", observer=taped)
        recording.close()
        tape = taped.tape
        parts: dict[str, list[float]] = {"open": [], "draw": [], "close": [], "observer alone": []}
        for i in range(repeats):
            t0 = time.process_time()
            recording = open_recording(f"again{i}", save=Path(d) / f"{i}.rrd")
            t1 = time.process_time()
            _hand(LabObserver(recording.canvas), tape)
            t2 = time.process_time()
            recording.close()
            t3 = time.process_time()
            _hand(LabObserver(_Blank()), tape)
            parts["open"].append(t1 - t0)
            parts["draw"].append(t2 - t1)
            parts["close"].append(t3 - t2)
            parts["observer alone"].append(time.process_time() - t3)
    table(f"The recorder on its own: the {len(tape):,} calls one standard campaign made, handed again to a new "
          f"observer and recording ({repeats} times; process CPU ms, Rerun's threads included)",
          ["part", "best ms", "median ms"],
          [[k, f"{1000 * min(v):.1f}", f"{1000 * statistics.median(v):.1f}"] for k, v in parts.items()])


def _hand(observer: LabObserver, tape: list[tuple[str, Any]]) -> None:
    for kind, item in tape:
        if kind == "note":
            observer.on_note(item)
        else:
            observer.on_envelope(item)
    observer.finish()


if __name__ == "__main__":
    isolated() if "--isolated" in sys.argv else main()
