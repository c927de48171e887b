"""What makes one stage of a lab its bottleneck: each device type's lab time per experiment, and the factor on its
steps' duration that makes it the busiest by a margin (the bench's bottleneck shapes, and training's draws of them)."""

from __future__ import annotations

import math

from twin.scenario.model import Scenario, expected_duration

#: How much more lab time per experiment a bottleneck stage takes than the busiest other stage.
MARGIN = 1.25


def stage_loads(s: Scenario) -> dict[str, float]:
    """Lab seconds each device type's instance spends on one experiment of the workflow: its steps' mean durations
    (a parameter a duration adds, at the step's value or its box's middle), setup and clean, ÷ its instances."""
    loads: dict[str, float] = {}
    for w in s.workflow:
        d = s.devices[w.device]
        param = d.duration.plus_param
        box = s.chemistry.parameters.get(param) if param else None
        given = {param: w.params.get(param, (box.low + box.high) / 2 if box is not None else 0.0)} if param else {}
        loads[w.device] = loads.get(w.device, 0.0) + expected_duration(d.duration, given, d.setup_s,
                                                                       d.clean_s) / d.instances
    return loads


def bottleneck(s: Scenario, name: str) -> float:
    """What to multiply ``name``'s ``duration.mean_s`` by to make it the lab's bottleneck: 2, or more where twice
    as long still leaves another stage busier (a spectrometer twice as slow behind a reactor three times as busy);
    0 where no factor can (its steps' duration is all a parameter's, ``mean_s: 0``)."""
    d = s.devices[name]
    if d.duration.mean_s <= 0:
        return 0.0
    loads = stage_loads(s)
    others = max((load for other, load in loads.items() if other != name), default=0.0)
    steps = sum(1 for w in s.workflow if w.device == name)
    scaled = steps * d.duration.mean_s / d.instances  # the part of its load the factor multiplies
    if not scaled or not others:
        return 2.0  # not in the workflow (a planner's routes use it), or the only stage: twice as long
    needed = (MARGIN * others - (loads[name] - scaled)) / scaled
    return max(2.0, math.ceil(needed * 10) / 10)
