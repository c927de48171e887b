"""A late watcher's catch-up: the history of a long campaign, page by page, as the lab serves it.

    python bench/bench_history.py [--experiments 1000]

A watcher that joins a running campaign (`twin watch`) asks for its history in pages of at most 500 rows
(`twin/runtime/decision_stream.py`), and the lab's event loop waits while each page is read. The journal of
a flaky_lab campaign of ``--experiments`` experiments (virtual time, memory bus) is paged through twice: as the
lab serves it (each page read alone), and as the baseline, each page cut from the whole journal read again (how
it was served before 2026-12-02). The table gives the worst page (the longest the lab's loop stood still) and the
whole catch-up.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.tables import table  # noqa: E402
from twin.campaign.journal import Journal  # noqa: E402
from twin.campaign.journal_read import as_messages  # noqa: E402
from twin.core.bus import MemoryBus  # noqa: E402
from twin.core.clock import LabClock  # noqa: E402
from twin.runtime import decision_stream  # noqa: E402
from twin.runtime.lab import run  # noqa: E402
from twin.tools.planner_bench import quiet_alerts  # noqa: E402


class _WholeJournalEachPage(Journal):
    """The baseline: every page cut from all the rows, read and converted again."""

    def rows(self, after: int = 0, limit: int | None = None) -> list[dict]:
        every = super().rows()
        as_messages(every)
        return every[after:] if limit is None else every[after:after + limit]


def catch_up(journal: Journal) -> tuple[int, int, float, float]:
    """Pages, rows, the worst page's seconds and all of them, for a watcher paging through ``journal``."""
    clock = LabClock("virtual")
    stream = decision_stream.DecisionStream(journal, MemoryBus(), clock, "bench", "c")

    async def pages() -> tuple[int, int, float, float]:
        after, n_pages, n_rows, worst = 0, 0, 0, 0.0
        t0 = time.perf_counter()
        while after is not None:
            t = time.perf_counter()
            page = json.loads(await stream.history("k", json.dumps({"after": after}).encode()))
            worst = max(worst, time.perf_counter() - t)
            n_pages, n_rows, after = n_pages + 1, n_rows + len(page["items"]), page["next"]
        return n_pages, n_rows, worst, time.perf_counter() - t0

    return clock.run(pages())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--experiments", type=int, default=1000)
    args = ap.parse_args()
    quiet_alerts()  # the campaign's device alerts: the table is what this bench is for
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "long.db"
        run(ROOT / "scenarios" / "flaky_lab.yaml", journal=db, bus="memory",
            overrides={"campaign.budget": args.experiments, "campaign.stop_on_target": False})
        rows = []
        for name, kind in (("each page read alone (served now)", Journal),
                           ("the whole journal read per page (before)", _WholeJournalEachPage)):
            journal = kind(db, append=True)
            n_pages, n_rows, worst, total = catch_up(journal)
            journal.close()
            rows.append([name, n_pages, f"{n_rows:,}", f"{1000 * worst:,.1f}", f"{total:,.2f}"])
        base = float(rows[1][4].replace(",", ""))
        for r in rows:
            r.append(f"{float(r[4].replace(',', '')) / base:.3f}")
    table(f"A late watcher's catch-up: flaky_lab, {args.experiments:,} experiments",
          ["history", "pages", "rows", "worst page, ms", "all, s", "÷ before"], rows)


if __name__ == "__main__":
    main()
