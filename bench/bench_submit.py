"""`twin submit` to a served lab, on this tree against an older revision: what the lab's checks and trial of a
submitted campaign add to the wait for its answer.

    python bench/bench_submit.py 28be0a6              # the revision before submitted campaigns were tried (~1 min)
    python bench/bench_submit.py 28be0a6 --runs 9

Each tree serves shared_lab's lab (no campaigns, scaled clock, Zenoh on loopback) in a process of its own, and is
sent the catalysis campaign ``--runs`` times under new names by ``python -m twin submit`` (this tree's client for
both); the trees take turns, one submission each. The table gives each tree's median and worst wall seconds from
starting the client to its exit, and each median ÷ the revision's.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tables import free_port, table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def serve(tree: Path, lab: Path, journals: Path) -> tuple[subprocess.Popen, str]:
    """The lab served by ``tree``'s code, once it says it is serving; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "twin", "lab", "serve", str(lab), "--listen", endpoint, "--speed",
                             "100", "--journal", str(journals)], cwd=journals.parent, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(tree)})
    line = proc.stderr.readline() if proc.stderr else ""
    if "serving lab" not in line:
        proc.kill()
        sys.exit(f"{tree}: the lab did not start: {line}")
    return proc, endpoint


def submit(campaign: Path, endpoint: str) -> float:
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "twin", "submit", str(campaign), "--lab", "shared", "--connect",
                           endpoint], cwd=ROOT, capture_output=True, text=True, timeout=120)
    took = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"submit failed: {done.stderr[-500:]}")
    return took


def main() -> None:
    rev = next((a for a in sys.argv[1:] if not a.startswith("--") and not a.isdigit()), "28be0a6")
    runs = int(sys.argv[sys.argv.index("--runs") + 1]) if "--runs" in sys.argv else 5
    raw = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    catalyst = next(c for c in raw.pop("campaigns") if c["name"] == "catalyst")
    with tempfile.TemporaryDirectory() as d:
        scratch, old = Path(d), Path(d) / "old"
        (scratch / "lab.yaml").write_text(yaml.safe_dump(raw))
        subprocess.run(["git", "worktree", "add", "-q", "--detach", str(old), rev], cwd=ROOT, check=True)
        labs: list[subprocess.Popen] = []
        try:
            trees = {rev: old, "this tree": ROOT}
            served = {}
            for name, tree in trees.items():
                (scratch / name).mkdir()
                proc, endpoint = serve(tree, scratch / "lab.yaml", scratch / name / "runs")
                labs.append(proc)
                served[name] = endpoint
            took: dict[str, list[float]] = {name: [] for name in trees}
            for i in range(runs):
                for name in trees:
                    campaign = scratch / f"c{i}.yaml"
                    campaign.write_text(yaml.safe_dump({**catalyst, "name": f"c{i}"}))
                    took[name].append(submit(campaign, served[name]))
        finally:
            for proc in labs:
                proc.terminate()
                proc.wait(timeout=60)
            subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=True)
    median = {name: statistics.median(v) for name, v in took.items()}
    table(f"`twin submit` of a campaign to a served lab, wall seconds, {runs} each, {rev} and this tree in turn",
          ["tree", "median s", "worst s", f"÷ {rev}"],
          [[name, f"{median[name]:.2f}", f"{max(took[name]):.2f}", f"{median[name] / median[rev]:.2f}"]
           for name in took])


if __name__ == "__main__":
    main()
