"""Asynchronous Gaussian-process Bayesian optimisation, aware of several targets at once.

One GP per output a target names (anisotropic Matérn 5/2 with a noise term,
scikit-learn), over the parameter box scaled to [0, 1] — on a log scale for
parameters that span a decade or more. The acquisition is the
probability that an experiment meets a target — for ``value ± tol`` the
posterior mass inside the window, for ``min``/``max`` the mass beyond the
bound, multiplied over the target's conditions. A batch goes round the unmet
targets, and every point already chosen or still running in the lab enters
the GPs as a *kriging believer* (its posterior mean as a fake observation), so
a batch spreads out and never repeats a pending experiment.
"""

from __future__ import annotations

import math
import random
import warnings
from typing import Any

import numpy as np

from agents.box import UnitBox
from agents.planners import LhsPlanner
from twin import Outcome, Proposal


class GpBoPlanner:
    plans_routes = False  # every experiment runs the workflow as written
    aims_at_targets = True  # chooses by the chance of meeting chemistry.targets: with none, it explores only

    def __init__(self, parameters: dict[str, Any], seed: int, targets: list[Any] = (), n_init: int = 6,
                 candidates: int = 2048, refit_every: int = 4, log_scale: bool = True, **_: Any) -> None:
        self.box = UnitBox(parameters, log_scale)
        self.names = self.box.names
        self.targets = list(targets)
        self.outputs = sorted({o for t in self.targets for o in t.outputs})
        self.n_init, self.n_candidates, self.refit_every = n_init, candidates, refit_every
        self.rng = np.random.default_rng(random.Random(f"gp-bo:{seed}").getrandbits(64))
        self._parameters, self._seed = parameters, seed
        self._design: LhsPlanner | None = None  # made when first asked: a planner only checked never imports scipy
        self._kernels: dict[str, Any] = {}
        self._fitted_at = -1
        self._turn = 0

    # -- proposals ----------------------------------------------------------
    def propose(self, n: int, history: list[Outcome], pending: list[dict[str, Any]]) -> list[Proposal]:
        done = [h for h in history if h.outputs]
        x, ys = self._data(done) if self.targets else (np.empty((0, 0)), {})
        # too few experiments that measured what the targets name (none, if no device outputs it): keep exploring
        if len(x) < self.n_init:
            if self._design is None:
                self._design = LhsPlanner(self._parameters, self._seed, budget=self.n_init)
            return self._design.propose(n, history, pending) or self._random(n)
        # where a device refused (infeasible): a candidate whose nearest tried point was refused is not proposed
        self._refused = np.array([self._unit(h.params) for h in history if getattr(h, "infeasible", False)])
        self._tried = np.vstack([x, self._refused]) if len(self._refused) else x
        believers = [self._unit(p) for p in pending]
        unmet = [t for t in self.targets if not any(self._meets(h.outputs, t) for h in done)] or self.targets
        out = []
        for _ in range(n):
            gps = self._fit(x, ys, believers, refit=len(done) != self._fitted_at)
            target = unmet[self._turn % len(unmet)]
            self._turn += 1
            cand = self._candidates(x, ys, target)
            best = cand[int(np.argmax(self._p_meets(gps, cand, target)))]
            believers.append(best)
            out.append(Proposal(self._params(best)))
        self._fitted_at = len(done)
        return out

    def _random(self, n: int) -> list[Proposal]:
        return [Proposal(self._params(self.rng.random(len(self.names)))) for _ in range(n)]

    # -- model ----------------------------------------------------------------
    def _data(self, done: list[Outcome]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        rows = [h for h in done if all(isinstance(h.outputs.get(o), (int, float)) and math.isfinite(h.outputs[o])
                                       for o in self.outputs)]
        x = np.array([self._unit(h.params) for h in rows])
        return x, {o: np.array([h.outputs[o] for h in rows], dtype=float) for o in self.outputs}

    def _fit(self, x: np.ndarray, ys: dict[str, np.ndarray], believers: list[np.ndarray], refit: bool):
        from sklearn.gaussian_process import GaussianProcessRegressor  # scipy and sklearn take seconds to import:
        # a planner made to be checked (twin validate) or that never fits need not wait for them
        gps = {}
        for o, y in ys.items():
            kernel = self._kernels.get(o)
            if kernel is None or refit and len(y) % self.refit_every == 0:
                kernel = self._fit_kernel(x, y)
                self._kernels[o] = kernel
            gp = GaussianProcessRegressor(kernel, optimizer=None, normalize_y=True).fit(x, y)
            if believers:
                xb = np.array(believers)
                gp = GaussianProcessRegressor(kernel, optimizer=None, normalize_y=True).fit(
                    np.vstack([x, xb]), np.concatenate([y, gp.predict(xb)]))
            gps[o] = gp
        return gps

    def _fit_kernel(self, x: np.ndarray, y: np.ndarray):
        from sklearn.exceptions import ConvergenceWarning
        from sklearn.gaussian_process import GaussianProcessRegressor
        from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

        d = x.shape[1]
        kernel = ConstantKernel(1.0, (1e-3, 1e3)) * Matern([0.3] * d, (1e-2, 10.0), nu=2.5) + WhiteKernel(1e-3, (1e-6, 1e-1))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            gp = GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=1,
                                          random_state=int(self.rng.integers(2**31))).fit(x, y)
        return gp.kernel_

    def _candidates(self, x: np.ndarray, ys: dict[str, np.ndarray], target: Any) -> np.ndarray:
        d = len(self.names)
        uniform = self.rng.random((self.n_candidates, d))
        closest = np.argsort(self._distance(ys, target))[:8]
        local = (x[closest][:, None, :] + self.rng.normal(0, 0.05, (len(closest), 64, d))).reshape(-1, d)
        return self._feasible(np.clip(np.vstack([uniform, local]), 0.0, 1.0))

    def _feasible(self, cand: np.ndarray) -> np.ndarray:
        """A nearest-neighbour feasibility model: keep the candidates closer to a point that ran than to one
        that was refused (all of them while nothing was refused, or if none would be left)."""
        refused = getattr(self, "_refused", np.empty((0, cand.shape[1])))
        if not len(refused):
            return cand
        ran = self._tried[: len(self._tried) - len(refused)]
        d_refused = np.min(np.linalg.norm(cand[:, None, :] - refused[None, :, :], axis=2), axis=1)
        d_ran = (np.min(np.linalg.norm(cand[:, None, :] - ran[None, :, :], axis=2), axis=1) if len(ran)
                 else np.full(len(cand), np.inf))
        keep = cand[d_ran < d_refused]
        return keep if len(keep) else cand

    def _distance(self, ys: dict[str, np.ndarray], target: Any) -> np.ndarray:
        dist = np.zeros(len(next(iter(ys.values()))))
        for o, c in target.outputs.items():
            y = ys[o]
            if c.value is not None:
                dist += np.abs(y - c.value) / c.tol
            if c.min is not None:
                dist += np.maximum(0, c.min - y)
            if c.max is not None:
                dist += np.maximum(0, y - c.max)
        return dist

    def _p_meets(self, gps: dict[str, Any], cand: np.ndarray, target: Any) -> np.ndarray:
        from scipy.stats import norm

        p = np.ones(len(cand))
        for o, c in target.outputs.items():
            mu, sd = gps[o].predict(cand, return_std=True)
            sd = np.maximum(sd, 1e-9)
            if c.value is not None:
                p *= norm.cdf((c.value + c.tol - mu) / sd) - norm.cdf((c.value - c.tol - mu) / sd)
            if c.min is not None:
                p *= norm.sf((c.min - mu) / sd)
            if c.max is not None:
                p *= norm.cdf((c.max - mu) / sd)
        return p

    @staticmethod
    def _meets(outputs: dict[str, Any], target: Any) -> bool:
        from twin import score

        return score(outputs, target) == 0

    # -- scaling ------------------------------------------------------------------
    def _unit(self, params: dict[str, Any]) -> np.ndarray:
        return self.box.unit(params)

    def _params(self, u: np.ndarray) -> dict[str, float]:
        return self.box.params(u)
