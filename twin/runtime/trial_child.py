"""The process that tries a campaign submitted to a served lab (``submitted_warnings`` in twin/runtime/trial.py):
the scenario as JSON on stdin, its one argument what the trial's warning ends with; it prints what
the checks and the trial warn of, as a JSON list."""

from __future__ import annotations

import contextlib
import io
import json
import sys

from twin.core.warnings_said import warnings_said
from twin.runtime.checks import check_campaign
from twin.runtime.trial import trial_warning
from twin.scenario import Scenario


def warned_of(text: str, then: str) -> list[str]:
    """The checks' warnings, then the trial's, of the scenario ``text`` (JSON)."""
    s = Scenario.model_validate_json(text)
    with warnings_said() as warned, contextlib.redirect_stdout(io.StringIO()):
        check_campaign(s)
    return [*warned.said, *[w for w in [trial_warning(s, "", then=then)] if w]]


if __name__ == "__main__":
    print(json.dumps(warned_of(sys.stdin.read(), sys.argv[1])))
