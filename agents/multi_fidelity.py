"""Multi-fidelity search: cheap DFT estimates first, then experiments on a corrected surrogate.

Phase 1 spends the free calculator on a space-filling set of compositions and
fits a GP to its band gaps. Phase 2 proposes real experiments (synthesis and
measurement, which cost money) where the probability of hitting the target is
highest under ``DFT surrogate + correction``: the correction is a second GP,
over composition *and* growth conditions, fitted to what the experiments
measured minus what DFT predicted — so the surrogate learns DFT's offset and
the growth physics DFT cannot see. Pending experiments enter the correction as
kriging believers, so a batch spreads out.
"""

from __future__ import annotations

import random
import warnings
from typing import Any

import numpy as np

from agents.box import UnitBox
from twin import Outcome, Proposal, RouteStep

PRIOR_CORRECTION_SD = 0.3  # eV: how far we believe DFT can be off before any experiment


class MultiFidelityPlanner:
    aims_at_targets = True  # chooses by the chance of meeting chemistry.targets: with none, it explores only

    def __init__(self, parameters: dict[str, Any], seed: int, targets: list[Any] = (), n_dft: int = 12,
                 dft_step: str = "compute", dft_device: str = "dft", dft_output: str = "band_gap_dft_ev",
                 dft_inputs: tuple[str, ...] = ("indium_fraction",), candidates: int = 2048, **_: Any) -> None:
        self.box = UnitBox(parameters, log_scale=False)
        self.names = self.box.names
        self.target = targets[0] if targets else None
        self.output, self.cond = next(iter(self.target.outputs.items())) if self.target else (None, None)
        self.dft_route = (RouteStep(dft_step, dft_device),)
        self.dft_output, self.n_dft, self.n_candidates = dft_output, n_dft, candidates
        self.dft_idx = [self.names.index(n) for n in dft_inputs]
        self.rng = np.random.default_rng(random.Random(f"mf:{seed}").getrandbits(64))
        self._dft_sent = 0

    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        out = []
        while len(out) < n and self._dft_sent < self.n_dft:
            u = self.rng.random(len(self.names))
            u[self.dft_idx[0]] = (self._dft_sent + self.rng.random()) / self.n_dft  # one per stratum
            self._dft_sent += 1
            out.append(Proposal(self._params(u), self.dft_route))
        dft = [h for h in history if h.outputs and self.dft_output in h.outputs]
        if len(out) == n or len(dft) < self.n_dft or self.target is None:
            return out  # experiments wait for the calculator's map
        exps = [h for h in history if h.outputs and self.output in h.outputs]
        dft_gp = self._gp(np.array([self._unit(h.params)[self.dft_idx] for h in dft]),
                          np.array([h.outputs[self.dft_output] for h in dft]))
        x = np.array([self._unit(h.params) for h in exps]).reshape(-1, len(self.names))
        resid = np.array([h.outputs[self.output] for h in exps]) - (dft_gp.predict(x[:, self.dft_idx]) if len(x) else 0)
        exp_pending = [self._unit(p) for p in pending if p]
        for _ in range(n - len(out)):
            cand = self.rng.random((self.n_candidates, len(self.names)))
            p_hit = self._p_hit(dft_gp, x, resid, exp_pending, cand)
            best = cand[int(np.argmax(p_hit))]
            exp_pending.append(best)
            out.append(Proposal(self._params(best)))
        return out

    def _p_hit(self, dft_gp, x, resid, believers, cand):
        from scipy.stats import norm  # here, as sklearn below: seconds of imports a lab only checked never needs
        from sklearn.gaussian_process import GaussianProcessRegressor

        mu_d, sd_d = dft_gp.predict(cand[:, self.dft_idx], return_std=True)
        if len(x) >= 2:
            xb = np.vstack([x, np.array(believers).reshape(-1, x.shape[1])]) if believers else x
            corr = self._gp(x, resid, normalize=False)
            rb = np.concatenate([resid, corr.predict(np.array(believers))]) if believers else resid
            corr = GaussianProcessRegressor(corr.kernel_, optimizer=None).fit(xb, rb)
            mu_c, sd_c = corr.predict(cand, return_std=True)
        else:
            mu_c = np.full(len(cand), resid.mean() if len(resid) else 0.0)
            sd_c = np.full(len(cand), PRIOR_CORRECTION_SD)
        mu, sd = mu_d + mu_c, np.sqrt(sd_d**2 + sd_c**2) + 1e-9
        c = self.cond
        if c.value is not None:
            p = norm.cdf((c.value + c.tol - mu) / sd) - norm.cdf((c.value - c.tol - mu) / sd)
        else:
            p = np.ones(len(cand))
            if c.min is not None:
                p *= norm.sf((c.min - mu) / sd)
            if c.max is not None:
                p *= norm.cdf((c.max - mu) / sd)
        return p

    def _gp(self, x: np.ndarray, y: np.ndarray, normalize: bool = True) -> Any:
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

        kernel = (ConstantKernel(1.0, (1e-3, 1e3)) * Matern([0.3] * x.shape[1], (1e-2, 10.0), nu=2.5)
                  + WhiteKernel(1e-3, (1e-6, 1e-1)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            return GaussianProcessRegressor(kernel, normalize_y=normalize, n_restarts_optimizer=1,
                                            random_state=int(self.rng.integers(2**31))).fit(x, y)

    def _unit(self, params: dict[str, Any]) -> np.ndarray:
        return self.box.unit(params)

    def _params(self, u: np.ndarray) -> dict[str, float]:
        return self.box.params(u)
