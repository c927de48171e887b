"""The spectrometer: renders a sample's spectrum, with noise, and extracts peaks by fitting.

A sample that waited degrades: its signal falls as exp(-age / stability_s)
and its band broadens, so a late measurement reads worse.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from devices.models import spectra, synthesis
from twin import DriverSetup, Refused, StepContext, StepResult

FEED_NM, PRODUCT_NM, BYPRODUCT_NM, BAND_NM = 450.0, 540.0, 640.0, 40.0
HC_EV_NM = 1239.84  # photon energy (eV) × wavelength (nm)
EDGE_WIDTH_NM = 4.0
MEASURED = frozenset({"qd", "film", "reaction", "crude", "purified"})  # the kinds of sample the models make
#: kinds the models make that are not measured, and what makes them measurable
UNMEASURED = {"feed": "a catalyst's feed, which a reactor's react makes a reaction"}


class Spectrometer:
    capabilities = frozenset({"measure", "lcms"})
    outputs = frozenset({"peak_nm", "fwhm_nm", "intensity", "band_gap_ev", "edge_nm", "yield", "selectivity",
                         "spectrum", "age_s", *synthesis.LCMS_OUTPUTS})
    chemistry_models = frozenset({"quantum_dots", "bandgap", "catalyst", "synthesis"})
    option_names: frozenset[str] = frozenset()  # it takes none
    makes_sample: frozenset[str] = frozenset()
    needs_sample = frozenset({"measure", "lcms"})

    def __init__(self, setup: DriverSetup) -> None:
        self.noise = setup.chemistry.noise
        self.stability_s = setup.chemistry.stability_s

    async def run(self, step: str, params: dict[str, Any], sample: dict | None, ctx: StepContext) -> StepResult:
        # what arrives is the workflow's doing, not the instrument's: refused at once, no strike against it
        if not sample:
            raise Refused("measure needs a sample: the workflow must make one first", infeasible=True)
        if sample.get("kind") not in MEASURED:
            kind = str(sample.get("kind"))
            what = f"{UNMEASURED[kind]}; " if kind in UNMEASURED else ""
            raise Refused(f"the spectrometer cannot measure a sample of kind {kind[:40]!r} ({what}it measures "
                          f"{', '.join(sorted(MEASURED))}): check the workflow's order", infeasible=True)
        await ctx.clock.sleep(ctx.draw_duration(params))
        if sample.get("kind") in ("crude", "purified"):  # a route's reaction: LC-MS
            return StepResult(synthesis.lcms(sample, params, ctx.clock.now(), self.stability_s, self.noise, ctx.rng),
                              sample)
        age = ctx.clock.now() - float(sample.get("t_made", ctx.clock.now()))
        keep = math.exp(-age / self.stability_s) if self.stability_s > 0 else 1.0
        if sample.get("kind") == "qd":
            bands = [(sample["peak_nm"], sample["fwhm_nm"] * (1 + 0.3 * (1 - keep)), sample["amplitude"] * keep)]
            y = spectra.render(bands, self.noise, ctx.rng)
            fit = spectra.fit_peak(y)
            outputs = {"peak_nm": fit["center"], "fwhm_nm": fit["fwhm"], "intensity": fit["height"]}
        elif sample.get("kind") == "film":
            y, edge_nm = self._absorption_edge(sample["band_gap_ev"], keep, ctx)
            outputs = {"band_gap_ev": HC_EV_NM / edge_nm, "edge_nm": edge_nm}
        else:  # a reaction's product
            conv, sel = sample["conversion"], sample["selectivity"]
            bands = [(FEED_NM, BAND_NM, 1 - conv), (PRODUCT_NM, BAND_NM, conv * sel * keep),
                     (BYPRODUCT_NM, BAND_NM, conv * (1 - sel))]
            y = spectra.render(bands, self.noise, ctx.rng)
            product = spectra.fit_peak(y, PRODUCT_NM - 30, PRODUCT_NM + 30)["height"]
            byproduct = max(spectra.fit_peak(y, BYPRODUCT_NM - 30, BYPRODUCT_NM + 30)["height"], 0.0)
            outputs = {"yield": 100 * product, "selectivity": 100 * product / max(product + byproduct, 1e-9)}
        outputs = {k: round(v, 4) for k, v in outputs.items()}
        grid = spectra.UV_GRID_NM if sample.get("kind") == "film" else spectra.GRID_NM
        outputs["spectrum"] = {"start_nm": float(grid[0]), "step_nm": float(grid[1] - grid[0]),
                               "y": np.round(y, 4).tolist()}
        outputs["age_s"] = round(age, 1)
        return StepResult(outputs, sample)

    def _absorption_edge(self, gap_ev: float, keep: float, ctx: StepContext) -> tuple[np.ndarray, float]:
        """An absorption edge at the band gap; its derivative is a peak, fitted like any other."""
        grid = spectra.UV_GRID_NM
        edge = HC_EV_NM / gap_ev
        y = keep / (1 + np.exp((grid - edge) / EDGE_WIDTH_NM)) + ctx.rng.normal(0.0, self.noise, grid.shape)
        slope = -np.gradient(np.convolve(y, np.ones(5) / 5, mode="same"), grid)
        return y, spectra.fit_peak(slope, grid=grid, lo=grid[3], hi=grid[-4])["center"]

    async def safe_state(self) -> None:
        """Shutter closed; nothing to undo."""
