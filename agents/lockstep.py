"""Several runs of one lab scheduled by one candidate policy in lockstep: one forward pass per step for all.

The first run takes the policy's best candidate (greedy); the others sample from its scores ÷ a temperature,
each in turn from ``temperatures``. Too high for the policy, a sample strays so far from the greedy run that
the best of 16 is hardly better than it; too low, it seldom leaves it. Self-labelling (``agents.imitation``)
learns from the best run; ``agents.rollout_plan`` follows it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from agents.candidates import ENCODING, CandidateEncoder, Observed
from twin import Assignment, Scenario, stepped

# `python bench/bench_sampling.py P.zip` (best of 16 ÷ greedy, 8 random shops): the CP-SAT-taught policy does best
# at temperature ¼ (0.958; 0.976 at 1), the self-labelled ones, sharper, at 1 (0.961; 0.978 at ¼): the sampled
# runs take turns at ½ and 1, good for both.
SAMPLE_TEMPERATURES = (0.5, 1.0)

#: Told each choice of each run: the run's number, its encoder (``encoded``: this state's candidates), the
#: observation and mask, the action taken and the assignments it made.
Seen = Callable[[int, CandidateEncoder, np.ndarray, np.ndarray, int, list[Assignment]], None]


def lockstep(lab: Scenario, scorer: torch.nn.Module, k: int, temperatures: tuple[float, ...] = SAMPLE_TEMPERATURES,
             encoding: str = ENCODING, seen: Seen | None = None, greedy_first: bool = True,
             generator: torch.Generator | None = None, held: Observed | None = None) -> list[Any]:
    """``k`` campaigns of ``lab`` (its seed for all), run to their ends; the summary of each, the greedy run's
    first (``greedy_first=False``: every run sampled). ``generator`` draws the samples (None: torch's own);
    ``held``: the range the policy's inputs are held in, as it decides in a lab (its file's observed range)."""
    runs = [(CandidateEncoder(lab, encoding), stepped(lab)) for _ in range(k)]
    for encoder, _ in runs:
        encoder.held = held
    try:
        live = [i for i in range(k) if not runs[i][1].done]  # a lab that ends before any decision asks none
        while live:
            encoded = [runs[i][0].encode(runs[i][1].view) for i in live]
            mask = torch.as_tensor(np.stack([m for _, m in encoded]))
            with torch.no_grad():
                logits = scorer(torch.as_tensor(np.stack([o for o, _ in encoded]))).masked_fill(~mask, -torch.inf)
            heat = torch.tensor([temperatures[(i - 1) % len(temperatures)] for i in live]).unsqueeze(1)
            probs = torch.distributions.Categorical(logits=logits / heat).probs
            best, drawn = logits.argmax(1), torch.multinomial(probs, 1, generator=generator).squeeze(1)
            for j, i in enumerate(live):
                encoder, c = runs[i]
                action = int(best[j] if i == 0 and greedy_first else drawn[j])
                assignments = encoder.decode(c.view, action)
                if seen is not None:
                    seen(i, encoder, *encoded[j], action, assignments)
                c.answer(assignments)
            live = [i for i in live if not runs[i][1].done]
        return [c.summary for _, c in runs]
    finally:
        for _, c in runs:
            c.close()
