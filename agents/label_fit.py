"""Fitting the candidate scorer to labelled choices: a labelled state (``Sample``), a batch of them laid out as the
policy reads them, and cross-entropy epochs over them (each row weighted: 1 for a teacher's label, its run's
advantage for the policy gradient)."""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch

from agents.candidates import FEATURES, GLOBALS, MAX_CANDIDATES, WAIT


@dataclass
class Sample:
    rows: np.ndarray  # (n, FEATURES)
    glob: np.ndarray  # (GLOBALS,)
    allowed: np.ndarray  # (n + 1,) bool: the candidates, then waiting
    taught: np.ndarray  # (n + 1,) bool: the teacher's choices among them
    weight: float = 1.0  # self-pg: the run's advantage (negative: a choice to make less likely)


def batch(samples: list[Sample]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(observations, allowed, taught) padded to the most candidates in the batch, laid out as the policy
    reads them (rows from the first, WAIT last)."""
    obs = np.zeros((len(samples), MAX_CANDIDATES * FEATURES + GLOBALS), np.float32)
    allowed = np.zeros((len(samples), MAX_CANDIDATES + 1), bool)
    taught = np.zeros_like(allowed)
    for b, s in enumerate(samples):
        k = len(s.rows)
        obs[b, :k * FEATURES] = s.rows.ravel()
        obs[b, MAX_CANDIDATES * FEATURES:] = s.glob
        allowed[b, :k], allowed[b, WAIT] = s.allowed[:k], s.allowed[k]
        taught[b, :k], taught[b, WAIT] = s.taught[:k], s.taught[k]
    return torch.as_tensor(obs), torch.as_tensor(allowed), torch.as_tensor(taught)


def imitation_loss(logits: torch.Tensor, allowed: torch.Tensor, taught: torch.Tensor,
                   weights: torch.Tensor) -> torch.Tensor:
    """−log P(the teacher's set of choices), the softmax taken over what is allowed, times each row's weight (1 for
    a label; self-pg: its run's advantage, so that the mean is REINFORCE's loss)."""
    masked = logits.masked_fill(~allowed, -1e9)
    return (weights * (torch.logsumexp(masked, 1) - torch.logsumexp(logits.masked_fill(~taught, -1e9), 1))).mean()


def fit(net: torch.nn.Module, data: list[Sample], epochs: int, optimizer: torch.optim.Optimizer,
        batch_size: int = 256, seed: int = 0) -> float:
    """Cross-entropy epochs over ``data`` (each row weighted by its ``weight``); the last epoch's mean loss."""
    rng = random.Random(seed)
    order = list(range(len(data)))
    last = 0.0
    for _ in range(epochs):
        rng.shuffle(order)
        losses = []
        for i in range(0, len(order), batch_size):
            chunk = [data[k] for k in order[i:i + batch_size]]
            obs, allowed, taught = batch(chunk)
            loss = imitation_loss(net(obs), allowed, taught, torch.tensor([s.weight for s in chunk]))
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            optimizer.step()
            losses.append(float(loss.detach()))
        last = sum(losses) / max(len(losses), 1)
    return last
