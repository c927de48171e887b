"""A `twin` command's start, on this tree against an older revision, back to back on this machine.

    python bench/bench_starts.py df2cac6     # the revision before the CLI imported the kernel lazily (~1 minute)
    python bench/bench_starts.py df2cac6 --runs 9

Each command runs as a user runs it, a fresh interpreter each time (``python -m twin ...``), the old tree and
this one alternately; the table gives each tree's median wall seconds and CPU seconds (user + system) over
the runs, and old ÷ new of the CPU: the process tests start ~140 of these, and a user types them.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tables import table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def commands(d: Path) -> list[tuple[str, list[str]]]:
    """What to start: ``{d}`` in an argument is a fresh scratch directory for each run."""
    qd = str(ROOT / "scenarios" / "quantum_dots.yaml")
    return [
        ("twin --help", ["--help"]),
        ("twin router --help", ["router", "--help"]),
        ("twin ctl status (no lab)", ["ctl", "status", "--lab", "qd", "--connect", "tcp/127.0.0.1:9", "--wait", "0.1"]),
        ("twin security init", ["security", "init", "{d}/sec", "--lab", "qd", "--device", "spectrometer"]),
        ("twin validate", ["validate", qd]),
        ("twin report", ["report", str(d / "qd.db")]),
        ("twin run quantum_dots", ["run", qd, "--quiet", "--journal", "{d}/run.db"]),
    ]


def start(tree: Path, args: list[str], scratch: Path) -> tuple[float, float]:
    """Wall and CPU seconds of one ``python -m twin ARGS`` on ``tree``."""
    with tempfile.TemporaryDirectory(dir=scratch) as d:
        argv = [a.replace("{d}", d) for a in args]
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "twin", *argv], cwd=scratch, env={**os.environ, "PYTHONPATH": str(tree)},
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    rev = next((a for a in sys.argv[1:] if not a.startswith("--") and not a.isdigit()), "df2cac6")
    runs = int(sys.argv[sys.argv.index("--runs") + 1]) if "--runs" in sys.argv else 5
    with tempfile.TemporaryDirectory() as d:
        scratch, old = Path(d), Path(d) / "old"
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(old), rev], cwd=ROOT, check=True)
        try:
            subprocess.run([sys.executable, "-m", "twin", "run", str(ROOT / "scenarios" / "quantum_dots.yaml"),
                            "--quiet", "--journal", str(scratch / "qd.db")], cwd=scratch, check=True,
                           stdout=subprocess.DEVNULL)
            rows = []
            for name, args in commands(scratch):
                took: dict[str, list[tuple[float, float]]] = {"old": [], "new": []}
                for _ in range(runs):
                    took["old"].append(start(old, args, scratch))
                    took["new"].append(start(ROOT, args, scratch))
                wall = {k: statistics.median(w for w, _ in v) for k, v in took.items()}
                cpu = {k: statistics.median(c for _, c in v) for k, v in took.items()}
                rows.append([name, f"{wall['old']:.2f}", f"{wall['new']:.2f}", f"{cpu['old']:.2f}",
                             f"{cpu['new']:.2f}", f"{cpu['old'] / cpu['new']:.2f}"])
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=True)
    table(f"A twin command's start (python -m twin …), medians of {runs} runs each, {rev} and this tree alternately",
          ["command", f"wall s, {rev}", "wall s, this tree", f"CPU s, {rev}", "CPU s, this tree", "CPU old ÷ new"],
          rows)


if __name__ == "__main__":
    main()
