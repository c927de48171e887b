"""A scenario's parameter box mapped to the unit cube (log scale for parameters spanning a decade)."""

from __future__ import annotations

from typing import Any

import numpy as np


class UnitBox:
    def __init__(self, parameters: dict[str, Any], log_scale: bool = True) -> None:
        self.names = list(parameters)
        self.lo = np.array([p.low for p in parameters.values()], dtype=float)
        self.hi = np.array([p.high for p in parameters.values()], dtype=float)
        self.log = (self.lo > 0) & (self.hi >= 10 * self.lo) if log_scale else np.zeros(len(self.lo), bool)
        self._lo, self._hi = (np.where(self.log, np.log(np.where(self.log, a, 1.0)), a) for a in (self.lo, self.hi))

    @property
    def dims(self) -> int:
        return len(self.names)

    def unit(self, params: dict[str, Any]) -> np.ndarray:
        v = np.array([float(params[n]) for n in self.names])
        v = np.where(self.log, np.log(np.maximum(v, 1e-300)), v)
        return (v - self._lo) / (self._hi - self._lo)

    def params(self, u: np.ndarray) -> dict[str, float]:
        v = self._lo + np.asarray(u) * (self._hi - self._lo)
        v = np.where(self.log, np.exp(np.where(self.log, v, 0.0)), v)
        return {n: float(min(max(x, a), b)) for n, x, a, b in zip(self.names, v, self.lo, self.hi)}
