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
               external: list[str] | None) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if record.wanted:
        _fail(TwinError(f"{s.name}: --save/--viewer/--serve do not record a lab of several campaigns yet; each "
                        "campaign's journal can be replayed (twin replay <journals>/<campaign>.db --save x.rrd)"))
    try:
        check(s)
        if not quiet and not json_out:
            err.print(f"{s.name}: {len(s.campaigns)} campaigns sharing the lab "
                      f"({', '.join(c.name for c in s.campaigns)}), {s.clock.mode} clock …", highlight=False)
        summary = run_shared(s, journal, external_devices=set(external or ()))
    except TwinError as exc:
        _fail(exc)
    if json_out:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        render_lab_summary(summary, console)
