"""The seed chapter's catalytic reaction, driven by the reactor's real temperature trace.

Instantaneous (empirical, as in the chapter): the attainable yield peaks near
450 K (a Gaussian of width 35 K) and the selectivity falls off above 500 K (a
logistic step). Over a run the conversion approaches its attainable value with
a first-order time constant, so yield and selectivity depend on the whole
temperature trajectory the reactor's controller produced, overshoot included.
"""

from __future__ import annotations

import math

import numpy as np

T_OPT_K = 450.0
WIDTH_K = 35.0
Y_MAX = 0.97
SEL_HIGH, SEL_DROP, T_SEL_K, SEL_WIDTH_K = 0.99, 0.40, 500.0, 8.0
TAU_REACTION_S = 600.0


def attainable_conversion(t_k: np.ndarray) -> np.ndarray:
    return Y_MAX * np.exp(-(((t_k - T_OPT_K) / WIDTH_K) ** 2))


def selectivity(t_k: np.ndarray) -> np.ndarray:
    return SEL_HIGH - SEL_DROP / (1 + np.exp(-(t_k - T_SEL_K) / SEL_WIDTH_K))


def run(trace_k: np.ndarray, dt_s: float) -> dict[str, float]:
    """Conversion, selectivity and yield (fractions) after a run with this temperature trace."""
    hold = len(trace_k) * dt_s
    conv = float(np.mean(attainable_conversion(trace_k))) * (1 - math.exp(-hold / TAU_REACTION_S))
    weights = attainable_conversion(trace_k) + 1e-12
    sel = float(np.sum(selectivity(trace_k) * weights) / np.sum(weights))
    return {"conversion": conv, "selectivity": sel, "yield": conv * sel}
