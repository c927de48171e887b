"""A DFT calculator: a band gap for a nominal composition, in lab-minutes and at no cost."""

from __future__ import annotations

from typing import Any

from devices.models import bandgap
from devices.synthesiser import need
from twin import DriverSetup, StepContext, StepResult


class DftCalculator:
    capabilities = frozenset({"compute"})
    makes_sample: frozenset[str] = frozenset()  # a calculation: no sample in, none out
    outputs = frozenset({"band_gap_dft_ev"})
    chemistry_models = frozenset({"bandgap"})
    option_names: frozenset[str] = frozenset()  # it takes none

    def __init__(self, setup: DriverSetup) -> None:
        pass

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        (x,) = need(params, "indium_fraction")
        await ctx.clock.sleep(ctx.draw_duration(params))
        return StepResult({"band_gap_dft_ev": round(bandgap.dft_band_gap_ev(x, float(ctx.rng.normal())), 4)})

    async def safe_state(self) -> None:
        """A killed calculation leaves nothing behind."""
