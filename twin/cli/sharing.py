"""``twin run`` of a lab that serves several campaigns (a scenario with ``campaigns:``)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

from twin.cli.common import _fail, console, err
from twin.core.errors import TwinError
from twin.runtime.checks import check
from twin.runtime.shared_run import run_shared
from twin.scenario import Scenario
from twin.view.report import render_lab_summary
from twin.view.watch import RecordOptions


def shared_lab(s: Scenario, journal: Path | None, record: RecordOptions, quiet: bool, json_out: bool,
               external: list[str] | None, runtime: str) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    unsupported = [flag for flag, given in (("--save/--viewer/--serve", record.wanted), ("--external", external),
                                            ("--runtime asyncio", runtime == "asyncio")) if given]
    if unsupported:
        _fail(TwinError(f"{s.name}: a lab of several campaigns runs on the fast runtime in virtual time, without "
                        f"{', '.join(unsupported)} (yet): run each campaign's own scenario for those"))
    try:
        check(s)
        if not quiet and not json_out:
            err.print(f"{s.name}: {len(s.campaigns)} campaigns sharing the lab "
                      f"({', '.join(c.name for c in s.campaigns)}), virtual time …", highlight=False)
        summary = run_shared(s, journal)
    except TwinError as exc:
        _fail(exc)
    if json_out:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        render_lab_summary(summary, console)
