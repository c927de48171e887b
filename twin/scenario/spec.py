"""What every part of the scenario model is built of: the strict base model and the bounded types."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, StringConstraints, Strict

#: Labs, device types, scenario names: Zenoh key chunks and file names (no '/', '*', '$', '#', '?', '..').
NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,62}$"
Name = Annotated[str, StringConstraints(pattern=NAME)]
#: Steps, parameters, outputs, targets: shown and journalled; any text of sensible length.
Label = Annotated[str, StringConstraints(min_length=1, max_length=64)]
#: Upper bounds: far beyond any real lab, far below what overflows a clock or a timer.
MAX_S = 1e7  # lab seconds (~116 days) for one duration
MAX_VALUE = 1e12  # a parameter's bound, a cost
Range = Annotated[tuple[float, float], Strict(False)]
IntRange = Annotated[tuple[int, int], Strict(False)]


class Spec(BaseModel):
    # strict: `budget: true` or `instances: "2"` is a mistake, not a number; no infinities or NaNs anywhere; a
    # field set from Python (`s.campaign.budget = -3` in a notebook) is checked as the file's would be
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, validate_default=True,
                              validate_assignment=True)
