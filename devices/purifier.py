"""A purification station (flash chromatography or recrystallisation): keeps most of a crude product and
little of its impurities."""

from __future__ import annotations

from typing import Any

from devices.models import synthesis
from twin import DriverSetup, Refused, StepContext, StepResult


class Purifier:
    capabilities = frozenset({"purify"})
    makes_sample = needs_sample = capabilities
    outputs: frozenset[str] = frozenset()
    chemistry_models = frozenset({"synthesis"})
    option_names: frozenset[str] = frozenset()  # it takes none

    def __init__(self, setup: DriverSetup) -> None:
        pass

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        if not sample or sample.get("kind") not in ("crude", "purified"):
            raise Refused("purify needs a reaction's crude product: the route must react first", infeasible=True)
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({}, synthesis.purify(sample, ctx.rng))

    async def safe_state(self) -> None:
        """Column flow stopped, fractions kept."""
