"""The robot synthesiser: makes a sample from an experiment's parameters."""

from __future__ import annotations

from typing import Any

from devices.models import bandgap, quantum_dots, synthesis
from twin import DriverSetup, StepContext, StepResult
from twin import DriverError


def need(params: dict[str, Any], *names: str) -> list[float]:
    missing = [n for n in names if n not in params]
    if missing:
        raise DriverError(f"missing parameter(s) {missing}; the scenario's chemistry.parameters must name them")
    return [float(params[n]) for n in names]


class Synthesiser:
    capabilities = frozenset({"synthesise", "prepare", "react"})
    makes_sample = capabilities
    outputs = frozenset({"diameter_nm"})
    chemistry_models = frozenset({"quantum_dots", "bandgap", "catalyst", "synthesis"})
    option_names = frozenset({"batch_sd_nm"})

    def __init__(self, setup: DriverSetup) -> None:
        self.model = setup.chemistry.model
        self.batch_sd_nm = float(setup.options.get("batch_sd_nm", 1.0))
        self.stability_s = setup.chemistry.stability_s
        self.failing = [str(x) for x in setup.chemistry.options.get("failing", [])]

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        if self.model == "synthesis":
            return await self._react(params, ctx)
        await ctx.clock.sleep(ctx.draw_duration(params))
        made = {"t_made": ctx.clock.now()}
        if self.model == "bandgap":
            x, t_c = need(params, "indium_fraction", "growth_temperature_c")
            return StepResult({}, {"kind": "film", "band_gap_ev": bandgap.film_band_gap_ev(x, t_c), **made})
        if self.model == "quantum_dots":
            c, t_c, t_s = need(params, "concentration_mm", "temperature_c", "time_s")
            qd = quantum_dots.emission(c, t_c + 273.15, t_s)
            qd["peak_nm"] += float(ctx.rng.normal(0.0, self.batch_sd_nm))
            return StepResult({"diameter_nm": round(qd["diameter_nm"], 4)}, {"kind": "qd", **qd, **made})
        return StepResult({}, {"kind": "feed", **made})

    async def _react(self, params: dict[str, Any], ctx: StepContext) -> StepResult:
        """One reaction of a route: set-up and work-up (the scenario's duration), then the reaction itself for a
        time drawn from its template's range (``params.hours``)."""
        if "reaction" not in params or "scale_mmol" not in params:
            raise DriverError("a reaction needs params 'reaction' (reactants>>product SMILES) and 'scale_mmol': "
                              "use the route planner (campaign.planner: route)")
        lo, hi = params.get("hours", (1.0, 1.0))
        await ctx.clock.sleep(ctx.draw_duration({}) + 3600 * float(ctx.rng.uniform(float(lo), float(hi))))
        try:
            crude = synthesis.react(params, ctx.clock.now(), self.stability_s, self.failing, ctx.rng)
        except (ValueError, TypeError, KeyError) as exc:
            raise DriverError(f"cannot run this reaction: {exc}") from None
        return StepResult({}, crude)

    async def safe_state(self) -> None:
        """Nothing hot or moving is left behind by a cancelled synthesis."""
