"""The robot synthesiser: makes a sample from an experiment's parameters."""

from __future__ import annotations

from typing import Any

from devices.models import bandgap, quantum_dots
from twin import DriverSetup, StepContext, StepResult
from twin import DriverError


def need(params: dict[str, Any], *names: str) -> list[float]:
    missing = [n for n in names if n not in params]
    if missing:
        raise DriverError(f"missing parameter(s) {missing}; the scenario's chemistry.parameters must name them")
    return [float(params[n]) for n in names]


class Synthesiser:
    capabilities = frozenset({"synthesise", "prepare"})
    outputs = frozenset({"diameter_nm"})
    chemistry_models = frozenset({"quantum_dots", "bandgap", "catalyst"})

    def __init__(self, setup: DriverSetup) -> None:
        self.model = setup.chemistry.model
        self.batch_sd_nm = float(setup.options.get("batch_sd_nm", 1.0))

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
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

    async def safe_state(self) -> None:
        """Nothing hot or moving is left behind by a cancelled synthesis."""
