"""The process that tries a campaign submitted to a served lab (``submitted_warning`` in twin/runtime/trial.py):
the scenario as JSON on stdin, its one argument what the trial's warning ends with; it prints the warning ('' if
none) as JSON."""

from __future__ import annotations

import json
import sys

from twin.runtime.trial import trial_warning
from twin.scenario import Scenario

if __name__ == "__main__":
    print(json.dumps(trial_warning(Scenario.model_validate_json(sys.stdin.read()), "", then=sys.argv[1])))
