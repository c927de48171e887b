"""The standard campaign on this tree against an older revision, back to back on this machine.

    python bench/bench_against.py ec785c7          # the revision before issue [1 of 7]
    python bench/bench_against.py fddbe61 --wide   # a wide lab instead: random 100x20 and 200x50 job shops, MWKR

Each tree runs the campaign in its own process (best of 3, imports warmed up),
old and new alternately twice; prints µs per experiment (per operation with
--wide: hundreds of steps ready at once, fifty devices) and the speed-up.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHILD = """
import sys, time, tempfile
from pathlib import Path
from twin import prepare, run
STANDARD = {"campaign.budget": 400, "campaign.stop_on_target": False,
            "devices.synthesiser.faults.mtbc_h": 0, "devices.reactor.faults.mtbc_h": 0,
            "devices.spectrometer.faults.mtbc_h": 0}
s = prepare(Path(sys.argv[1]) / "scenarios/flaky_lab.yaml", overrides=STANDARD, bus="memory")
kept = tempfile.TemporaryDirectory()  # removed as the child exits
d = Path(kept.name)
kw = {"runtime": sys.argv[2]} if sys.argv[2] != "-" else {}
run(s, journal=d / "w.db", overrides={"campaign.budget": 2}, **kw)
best = float("inf")
for _ in range(3):
    t0 = time.perf_counter()
    run(s, journal=d / "j.db", **kw)
    best = min(best, time.perf_counter() - t0)
print(1e6 * best / 400)
"""


# a random shop (Taillard's way) of JOBS x MACHINES run under MWKR: µs per operation, best of 2
WIDE = """
import random, sys, tempfile, time
from pathlib import Path
from twin import prepare, run
jobs, machines = int(sys.argv[2]), int(sys.argv[3])
rng = random.Random(1)
kept = tempfile.TemporaryDirectory()  # removed as the child exits
d = Path(kept.name)
lines = [f"{jobs} {machines}"]
for _ in range(jobs):
    order = rng.sample(range(machines), machines)
    lines.append(" ".join(f"{m} {rng.randint(1, 99)}" for m in order))
(d / "shop.txt").write_text("\\n".join(lines) + "\\n")
s = prepare(Path(sys.argv[1]) / "scenarios/jobshop.yaml", bus="memory",
            overrides={"jobshop.file": str(d / "shop.txt"), "campaign.scheduler": "mwkr"})
best = float("inf")
for _ in range(2):
    t0 = time.perf_counter()
    run(s, journal=d / f"j{_}.db")
    best = min(best, time.perf_counter() - t0)
print(1e6 * best / (jobs * machines))
"""


def measure(tree: Path, *args: str, child: str = CHILD) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", child, str(tree), *args], cwd=tempfile.gettempdir(), env=env,
                         capture_output=True, text=True, check=True).stdout
    return float(out.strip().splitlines()[-1])


def main() -> None:
    rev = next((a for a in sys.argv[1:] if not a.startswith("--")), "ec785c7")
    wide = "--wide" in sys.argv
    with tempfile.TemporaryDirectory() as d:
        old = Path(d) / "old"
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(old), rev], cwd=ROOT, check=True)
        try:
            if wide:
                _wide(rev, old)
                return
            rows = {"old": [], "asyncio": [], "fast": []}
            for _ in range(2):
                rows["old"].append(measure(old, "-"))
                rows["asyncio"].append(measure(ROOT, "asyncio"))
                rows["fast"].append(measure(ROOT, "fast"))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=True)
    base = min(rows["old"])
    print("\nThe standard campaign (flaky_lab, 400 experiments, memory bus), µs per experiment, best of 6")
    print("| tree | µs/exp | speed-up |\n|---|---|---|")
    print(f"| {rev} | {base:,.0f} | 1.00 |")
    for name in ("asyncio", "fast"):
        print(f"| this tree, {name} runtime | {min(rows[name]):,.0f} | {base / min(rows[name]):.2f} |")


def _wide(rev: str, old: Path) -> None:
    print("\nRandom job shops under MWKR (memory bus, fast runtime), µs per operation, best of 4 (old and new "
          "alternately)")
    print(f"| shop | {rev} | this tree | speed-up |\n|---|---|---|---|")
    for jobs, machines in ((100, 20), (200, 50)):
        times: dict[str, list[float]] = {"old": [], "new": []}
        for _ in range(2):
            times["old"].append(measure(old, str(jobs), str(machines), child=WIDE))
            times["new"].append(measure(ROOT, str(jobs), str(machines), child=WIDE))
        a, b = min(times["old"]), min(times["new"])
        print(f"| {jobs}×{machines} | {a:,.0f} | {b:,.0f} | {a / b:.2f} |")


if __name__ == "__main__":
    main()
