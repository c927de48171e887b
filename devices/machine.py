"""A job-shop machine: runs an operation for exactly its given duration."""

from __future__ import annotations

from typing import Any

from twin import DriverSetup, StepContext, StepResult


class Machine:
    capabilities = frozenset({"op"})
    option_names: frozenset[str] = frozenset()  # it takes none
    outputs: frozenset[str] = frozenset()

    def __init__(self, setup: DriverSetup) -> None:
        pass

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({}, sample)

    async def safe_state(self) -> None:
        """Nothing to undo."""
