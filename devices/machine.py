"""A machine that only keeps time: each step lasts its drawn duration and hands the sample on unchanged. A
job shop's machines are these (step `op`), and so is a twin that stands in for a real instrument when only
its timing matters (`twin: {driver: machine}`: training a scheduler, a what-if of device counts). It runs the
steps `options.steps` lists, which the lab fills with its device type's `steps` when the scenario gives none."""

from __future__ import annotations

from typing import Any

from twin import DriverSetup, StepContext, StepResult


class Machine:
    option_names = frozenset({"steps"})
    outputs: frozenset[str] = frozenset()
    makes_sample: frozenset[str] = frozenset()  # it passes on the sample it was given

    def __init__(self, setup: DriverSetup) -> None:
        steps = setup.options.get("steps")
        if not isinstance(steps, list) or not steps or not all(isinstance(s, str) and s for s in steps):
            raise ValueError(f"options.steps must be a list of step names, e.g. [measure] (got {steps!r:.80})")
        self.capabilities = frozenset(steps)

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({}, sample)

    async def safe_state(self) -> None:
        """Nothing to undo."""
