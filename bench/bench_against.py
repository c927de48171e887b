"""The standard campaign on this tree against an older revision, back to back on this machine.

    python bench/bench_against.py ec785c7          # the revision before issue [1 of 7]

Each tree runs the campaign in its own process (best of 3, imports warmed up),
old and new alternately twice; prints µs per experiment and the speed-up.
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
d = Path(tempfile.mkdtemp())
kw = {"runtime": sys.argv[2]} if sys.argv[2] != "-" else {}
run(s, journal=d / "w.db", overrides={"campaign.budget": 2}, **kw)
best = float("inf")
for _ in range(3):
    t0 = time.perf_counter()
    run(s, journal=d / "j.db", **kw)
    best = min(best, time.perf_counter() - t0)
print(1e6 * best / 400)
"""


def measure(tree: Path, runtime: str) -> float:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([sys.executable, "-c", CHILD, str(tree), runtime], cwd=tempfile.gettempdir(), env=env,
                         capture_output=True, text=True, check=True).stdout
    return float(out.strip().splitlines()[-1])


def main() -> None:
    rev = sys.argv[1] if len(sys.argv) > 1 else "ec785c7"
    with tempfile.TemporaryDirectory() as d:
        old = Path(d) / "old"
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(old), rev], cwd=ROOT, check=True)
        try:
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


if __name__ == "__main__":
    main()
