"""``labtwin/SynthesisRoute-v0``: retrosynthesis as a game, one reaction a move.

An episode starts from a target molecule (drawn from the training targets, forward-made from the stock, or
given: ``reset(options={"target": SMILES})``). The observation is the Morgan fingerprint of the molecule to
make next (the first one still open, depth first) — what the expansion prior reads, so a policy trained here
is a prior for MCTS as it is. An action is a template, applied backwards to that molecule;
``action_masks()`` allows only templates that apply (MaskablePPO reads it). The reactants it proposes (the
first disconnection, if several) that are not in stock are opened in turn.

Reward: when nothing is open — the route reaches stock — ``1 − step_penalty × (reactions − 1) −
cost_weight × log10(1 + € per g of what it buys)``; −1 when the next molecule has no template that applies
or the route would pass ``max_steps`` reactions (the episode ends, ``terminated``).
"""

from __future__ import annotations

import math
import random
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from agents.rendering import METADATA, render_mode_of
from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.policy import BITS, fingerprint
from agents.routes.search import Expander
from agents.routes.stock import Stock
from agents.routes.targets import target_set
from agents.routes.templates import Template, canonical

ENV_ID = "labtwin/SynthesisRoute-v0"


class SynthesisRouteEnv(gym.Env):
    metadata = METADATA

    def __init__(self, templates: tuple[Template, ...] | None = None, stock: Stock | None = None,
                 targets: list[str] | None = None, n_targets: int = 200, max_steps: int = 6,
                 step_penalty: float = 0.1, cost_weight: float = 0.05, seed: int = 0,
                 expander: Expander | None = None, render_mode: str | None = None) -> None:
        """``render_mode`` ``"rgb_array"``: ``render()`` draws the target, the molecules still to make and those
        bought so far (RDKit)."""
        self.render_mode = render_mode_of(render_mode)
        self.templates = templates or template_file.load()
        self.stock = stock or stock_file.load()
        self.targets = list(targets) if targets else [t.smiles for t in target_set(self.templates, self.stock,
                                                                                   n_targets)]
        self.max_steps, self.step_penalty, self.cost_weight = max_steps, step_penalty, cost_weight
        self.expand = expander or Expander(self.templates)  # shared across episodes: molecules recur
        self.index = {t.name: i for i, t in enumerate(self.templates)}
        self.observation_space = spaces.Box(0.0, 1.0, (BITS,), np.float32)
        self.action_space = spaces.Discrete(len(self.templates))
        self._rng = random.Random(seed)
        self.open: list[str] = []
        self.route: list[tuple[str, tuple[str, ...], str]] = []  # (template, reactants, product)
        self.bought: set[str] = set()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._rng = random.Random(seed)
        target = (options or {}).get("target") or self._rng.choice(self.targets)
        smiles = canonical(target)
        if smiles is None:
            raise ValueError(f"not a valid SMILES: {target!r}")
        if smiles in self.stock:
            raise ValueError(f"{smiles} is in stock: there is no route to find")
        self.target, self.open, self.route, self.bought = smiles, [smiles], [], set()
        return self._obs(), {"target": smiles}

    def action_masks(self) -> np.ndarray:
        mask = np.zeros(len(self.templates), dtype=bool)
        if self.open:
            for r in self.expand(self.open[0]):
                mask[self.index[r.template.name]] = True
        return mask

    def step(self, action: int):
        molecule = self.open[0]
        reaction = next((r for r in self.expand(molecule) if self.index[r.template.name] == int(action)), None)
        if reaction is None:  # masked out: a policy that ignores the mask loses the episode
            return self._obs(), -1.0, True, False, self._info("the template does not apply")
        self.open.pop(0)
        self.route.append((reaction.template.name, reaction.reactants, molecule))
        made = {p for _, _, p in self.route}
        for x in reaction.reactants:
            if x in self.stock:
                self.bought.add(x)
            elif x not in self.open and x not in made:
                self.open.append(x)
        if not self.open:
            return self._obs(), self._solved_reward(), True, False, self._info("solved")
        if len(self.route) >= self.max_steps:
            return self._obs(), -1.0, True, False, self._info(f"no route within {self.max_steps} reactions")
        if not self.action_masks().any():
            return self._obs(), -1.0, True, False, self._info(f"no template applies to {self.open[0]}")
        return self._obs(), 0.0, False, False, self._info("")

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        from rdkit import Chem
        from rdkit.Chem import Draw

        shown = [(self.target, "target"), *((m, "to make") for m in self.open if m != self.target),
                 *((m, "bought") for m in sorted(self.bought))][:8]
        image = Draw.MolsToGridImage([Chem.MolFromSmiles(m) for m, _ in shown], molsPerRow=4, subImgSize=(160, 160),
                                     legends=[why for _, why in shown])
        return np.asarray(image.convert("RGB"), dtype=np.uint8)

    def _solved_reward(self) -> float:
        eur = sum((self.stock.get(x).eur_per_g or 0.0) for x in self.bought)
        return 1.0 - self.step_penalty * (len(self.route) - 1) - self.cost_weight * math.log10(1 + eur)

    def _obs(self) -> np.ndarray:
        return fingerprint(self.open[0]) if self.open else np.zeros(BITS, np.float32)

    def _info(self, why: str) -> dict[str, Any]:
        return {"target": self.target, "reactions": len(self.route), "solved": not self.open, "why": why,
                "route": list(self.route), "bought": sorted(self.bought)}

