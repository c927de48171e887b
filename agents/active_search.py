"""`campaign.rollout_search: active`: playing a lab ahead with a copy of the policy that learns that lab as it plays.

The ``campaign.rollouts`` runs are played in rounds of 32 (``agents.rollout_plan.ROUND``). After each round, the
copy takes one policy-gradient pass on the round's sampled runs, each run's choices weighted by how much better than
the round's mean it ended (as ``training.teacher: self-pg`` does over many labs; here on the one lab to be run). The
next round samples from the tuned copy, nearer to what worked on this lab. This is efficient active search (Hottung,
Kwon and Tierney, 2022) with every weight of the small network tuned. The policy file is not changed. The lab follows
the best run of all rounds, as with plain sampling.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from agents.candidates import CandidateEncoder
from agents.imitation import PG_BATCH, advantage_weighted, chosen
from agents.label_fit import Sample, fit

LEARNING_RATE = 1e-3  # ten times self-pg's: one lab, learnt for the few rounds it is played


class ActiveSearch:
    """A copy of ``scorer`` tuned on one lab between rounds of runs; ``net`` scores the next round's candidates."""

    def __init__(self, scorer: torch.nn.Module, seed: int) -> None:
        self.net = copy.deepcopy(scorer)
        self.net.eval()
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=LEARNING_RATE)
        self.seed, self.rounds = seed, 0
        self.runs: list[list[Sample]] = []

    def start(self, runs: int) -> None:
        """A round of ``runs`` runs begins."""
        self.runs = [[] for _ in range(runs)]

    def seen(self, run: int, encoder: CandidateEncoder, obs: np.ndarray, mask: np.ndarray, action: int) -> None:
        """Run ``run`` chose ``action`` in the state ``obs``."""
        self.runs[run].append(chosen(encoder, obs, mask, action))

    def learn(self, objectives: list[float], greedy_first: bool) -> None:
        """One gradient pass on the round just played (``objectives``: each run's). The greedy run, if the round
        has one, is left out: it is not drawn from the policy's distribution, which the gradient is of."""
        runs, scores = self.runs, np.asarray(objectives, dtype=float)
        if greedy_first:
            runs, scores = runs[1:], scores[1:]
        self.net.train()
        fit(self.net, advantage_weighted(runs, scores), 1, self.optimizer, batch_size=PG_BATCH,
            seed=self.seed + self.rounds)
        self.net.eval()
        self.rounds += 1
        self.runs = []
