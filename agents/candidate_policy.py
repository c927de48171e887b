"""The candidate-scoring policy: one shared network scores every (ready step, free device) row.

An SB3 ``MaskableActorCriticPolicy`` whose action and value heads read the observation of
``agents.candidates`` directly (the features extractor flattens, the MLP extractor is empty):

- each valid row ``x_i`` is embedded, ``h_i = φ(x_i)``;
- the lab's context is the masked mean and max of the ``h_i`` with the global features ``g``;
- candidate ``i`` scores ``v · tanh(A h_i + B context)``, waiting scores ``ω(context)``; MaskablePPO's mask leaves
  the rows that exist (and waiting, when allowed) and takes a softmax over them;
- the value is ``ρ(context)``.

So the parameters do not depend on how many candidates there are, and a row is scored in the light of
all the others (a DeepSets network: permutation-invariant context, shared scorer). SB3 expresses it
cleanly: only the heads are replaced, PPO, masking, rollout buffers and saving are SB3's own.
"""

from __future__ import annotations

from typing import Any

import torch
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from torch import nn

from agents.candidates import FEATURES, GLOBALS, MAX_CANDIDATES

HIDDEN = 64


def width(observation_size: int) -> int:
    """The features per row of an observation this long (``agents.candidates.WIDTHS``: a policy of an earlier
    encoding reads fewer)."""
    return (observation_size - GLOBALS) // MAX_CANDIDATES


def _rows(obs: torch.Tensor, features: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rows, validity, globals), the rows cut to the most any observation of the batch has: candidates are
    packed from the first row on, so the padding after them costs nothing."""
    rows = obs[:, :MAX_CANDIDATES * features].reshape(-1, MAX_CANDIDATES, features)
    n = max(1, int(rows[:, :, 0].sum(dim=1).max().item()))
    rows = rows[:, :n]
    return rows, rows[:, :, :1], obs[:, MAX_CANDIDATES * features:]


class _Sets(nn.Module):
    """Rows → (per-row embeddings, context)."""

    def __init__(self, features: int = FEATURES) -> None:
        super().__init__()
        self.features = features
        self.embed = nn.Sequential(nn.Linear(features, HIDDEN), nn.Tanh(), nn.Linear(HIDDEN, HIDDEN), nn.Tanh())
        self.context_dim = 2 * HIDDEN + GLOBALS

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rows, valid, glob = _rows(obs, self.features)
        h = self.embed(rows) * valid
        n = valid.sum(dim=1).clamp(min=1.0)
        mean = h.sum(dim=1) / n
        top = (h - 1e4 * (1 - valid)).max(dim=1).values * (valid.sum(dim=1) > 0.5).float()
        return h, torch.cat([mean, top, glob], dim=1)


class CandidateScorer(nn.Module):
    """The action head: logits for every row and for waiting (rows past the candidates get 0: masked)."""

    def __init__(self, features: int = FEATURES) -> None:
        super().__init__()
        self.sets = _Sets(features)
        # score_i = v · tanh(A h_i + B context + b): B context is computed once per observation, not per row
        self.row = nn.Linear(HIDDEN, HIDDEN)
        self.context = nn.Linear(self.sets.context_dim, HIDDEN, bias=False)
        self.out = nn.Linear(HIDDEN, 1)
        self.wait = nn.Sequential(nn.Linear(self.sets.context_dim, HIDDEN), nn.Tanh(), nn.Linear(HIDDEN, 1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        h, context = self.sets(obs)
        scores = self.out(torch.tanh(self.row(h) + self.context(context).unsqueeze(1))).squeeze(-1)
        logits = obs.new_zeros(obs.shape[0], MAX_CANDIDATES + 1)
        logits[:, :scores.shape[1]] = scores
        logits[:, MAX_CANDIDATES] = self.wait(context).squeeze(-1)
        return logits


class CandidateCritic(nn.Module):
    def __init__(self, features: int = FEATURES) -> None:
        super().__init__()
        self.sets = _Sets(features)
        self.value = nn.Sequential(nn.Linear(self.sets.context_dim, HIDDEN), nn.Tanh(), nn.Linear(HIDDEN, 1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.value(self.sets(obs)[1])


class CandidatePolicy(MaskableActorCriticPolicy):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["net_arch"] = []  # the heads read the flattened observation themselves
        super().__init__(*args, **kwargs)

    def _build(self, lr_schedule) -> None:
        self._build_mlp_extractor()
        features = width(self.observation_space.shape[0])
        self.action_net = CandidateScorer(features)
        self.value_net = CandidateCritic(features)
        if self.ortho_init:
            for module, gain in ((self.action_net, 2 ** 0.5), (self.value_net, 2 ** 0.5)):
                module.apply(lambda m, g=gain: self.init_weights(m, gain=g))
            for head, gain in ((self.action_net.out, 0.01), (self.action_net.wait[-1], 0.01),
                               (self.value_net.value[-1], 1.0)):
                self.init_weights(head, gain=gain)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)


def widened(state: dict[str, torch.Tensor], features: int = FEATURES) -> dict[str, torch.Tensor]:
    """A state of a policy that read narrower rows (an earlier encoding), for one that reads ``features``: the new
    columns enter with weight 0, so the widened policy decides as the old one did until it is trained further."""
    out = dict(state)
    for key, w in state.items():
        if key.endswith("sets.embed.0.weight") and w.shape[1] < features:
            out[key] = torch.cat([w, w.new_zeros(w.shape[0], features - w.shape[1])], dim=1)
    return out
