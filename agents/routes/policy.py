"""A learned expansion policy for route search: which templates to try first on a molecule.

A small network reads a molecule's Morgan fingerprint (radius 2, 2048 bits) and scores every template; MCTS
takes a reaction's prior from its template's softmax probability (shared among the reactions one template
proposes). It is taught by imitation, AiZynthFinder's way: each step of a known route — here the routes the
training targets were made by (``agents.routes.targets``, seeds held-out targets never use) — is a molecule
labelled with the template that made it.
"""

from __future__ import annotations

import json
import random
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from rdkit import Chem
from rdkit.Chem import rdFingerprintGenerator
from torch import nn

from agents.routes.search import Reaction
from agents.routes.templates import Template
from twin import not_a_file, written_whole

BITS = 2048
HIDDEN = 256
MAX_WEIGHTS_BYTES = 256 * 2**20  # what a prior's .pt may unpack to: the shipped one is 2.1 MB
MAX_DESCRIPTION_BYTES = 16 * 2**20  # its .json: a few kB as training writes it
_MORGAN = rdFingerprintGenerator.GetMorganGenerator(radius=2, fpSize=BITS)


def fingerprint(smiles: str) -> np.ndarray:
    return _MORGAN.GetFingerprintAsNumPy(Chem.MolFromSmiles(smiles)).astype(np.float32)


class TemplateScorer(nn.Module):
    def __init__(self, templates: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(BITS, HIDDEN), nn.ReLU(), nn.Dropout(0.2), nn.Linear(HIDDEN, templates))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class LearnedPrior:
    """``prior(molecule, reactions)`` for ``agents.routes.mcts.mcts``: each reaction's share of its template's
    probability on the molecule."""

    def __init__(self, scorer: TemplateScorer, names: Sequence[str]) -> None:
        self.scorer, self.index = scorer.eval(), {n: i for i, n in enumerate(names)}
        self.cache: dict[str, np.ndarray] = {}

    def probabilities(self, molecule: str) -> np.ndarray:
        if molecule not in self.cache:
            with torch.no_grad():
                logits = self.scorer(torch.as_tensor(fingerprint(molecule)).unsqueeze(0))[0]
            self.cache[molecule] = torch.softmax(logits, 0).numpy()
        return self.cache[molecule]

    def __call__(self, molecule: str, reactions: Sequence[Reaction]) -> list[float]:
        p = self.probabilities(molecule)
        per: dict[str, int] = {}
        for r in reactions:
            per[r.template.name] = per.get(r.template.name, 0) + 1
        return [float(p[self.index[r.template.name]]) / per[r.template.name] if r.template.name in self.index
                else 1e-3 for r in reactions]

    def ranked(self, molecule: str) -> list[str]:
        """The templates, most likely first."""
        names = sorted(self.index, key=self.index.get)
        return [names[i] for i in np.argsort(-self.probabilities(molecule))]


def examples(targets) -> list[tuple[str, str]]:
    """(molecule, template name) for every step of the targets' routes."""
    return [(product, name) for t in targets for name, _, product in t.route]


def train_prior(templates: tuple[Template, ...], pairs: list[tuple[str, str]], epochs: int = 20, seed: int = 0,
                on_epoch=None) -> TemplateScorer:
    torch.manual_seed(seed)
    names = [t.name for t in templates]
    index = {n: i for i, n in enumerate(names)}
    x = torch.as_tensor(np.stack([fingerprint(m) for m, _ in pairs]))
    y = torch.as_tensor([index[n] for _, n in pairs])
    scorer = TemplateScorer(len(names))
    optimizer = torch.optim.Adam(scorer.parameters(), lr=1e-3, weight_decay=1e-5)
    order = list(range(len(pairs)))
    rng = random.Random(seed)
    for epoch in range(epochs):
        rng.shuffle(order)
        scorer.train()
        total = 0.0
        for i in range(0, len(order), 128):
            batch = order[i:i + 128]
            loss = nn.functional.cross_entropy(scorer(x[batch]), y[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * len(batch)
        if on_epoch:
            on_epoch(epoch + 1, total / len(order))
    return scorer.eval()


def save_prior(scorer: TemplateScorer, templates: tuple[Template, ...], path: Path, **meta) -> None:
    path = Path(path)
    with written_whole(path.with_suffix(".pt")) as partial:
        torch.save(scorer.state_dict(), partial)
    with written_whole(path.with_suffix(".json")) as partial:
        partial.write_text(json.dumps({"kind": "route-prior", "templates": [t.name for t in templates], "bits": BITS,
                                       **meta}, indent=1))


def _unpacked_bytes(weights: Path) -> int:
    """What torch's zip of weights would unpack to (its entries may be deflated: a few kB can say gigabytes)."""
    try:
        with zipfile.ZipFile(weights) as archive:
            return sum(item.file_size for item in archive.infolist())
    except (zipfile.BadZipFile, OSError):
        return 0  # not a zip: torch.load says what is wrong with it


def load_prior(path: Path, templates: tuple[Template, ...]) -> LearnedPrior:
    path = Path(path)
    meta_file = path.with_suffix(".json")
    if not meta_file.exists() or not path.with_suffix(".pt").exists():
        raise FileNotFoundError(f"{path}: a route prior is a .pt file with a .json beside it; train one with "
                                f"`python -m agents.routes.train --out {path}`")
    for part in (meta_file, path.with_suffix(".pt")):
        if why := not_a_file(part):
            raise ValueError(f"{part} {why}; a route prior is a .pt file with a .json beside it")
    try:
        if meta_file.stat().st_size > MAX_DESCRIPTION_BYTES:
            raise ValueError(f"{meta_file.stat().st_size:,} bytes, where training writes a few kB")
        meta = json.loads(meta_file.read_text())
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:  # the last: JSON nested too deep
        raise ValueError(f"{meta_file}: not a route prior's description ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("templates", []), list):
        raise ValueError(f"{meta_file}: not a route prior's description (an object naming its templates)")
    names = meta.get("templates", [])
    missing = sorted(set(t.name for t in templates) - set(names))
    if meta.get("kind") != "route-prior" or meta.get("bits") != BITS:
        raise ValueError(f"{path} is not a route prior of this labtwin ({meta.get('kind')}, {meta.get('bits')} bits)")
    if missing:
        raise ValueError(f"{path} was trained on other templates: it does not know {missing[:3]}"
                         f"{' …' if len(missing) > 3 else ''}; retrain it on this template file (python -m "
                         f"agents.routes.train --templates FILE --out P) or search without one (--prior none)")
    weights = path.with_suffix(".pt")
    unpacked = _unpacked_bytes(weights)
    if unpacked > MAX_WEIGHTS_BYTES:
        raise ValueError(f"{weights}: would unpack to {unpacked / 2**20:,.0f} MB, more than a route prior does "
                         f"({MAX_WEIGHTS_BYTES / 2**20:,.0f} MB at most; a zip bomb?); nothing was loaded")
    scorer = TemplateScorer(len(names))
    try:
        scorer.load_state_dict(torch.load(weights, weights_only=True))
    except Exception as exc:  # torch's errors for a damaged or foreign file are of many types
        raise ValueError(f"{path.with_suffix('.pt')}: not this prior's weights ({type(exc).__name__}); "
                         "train it again with `python -m agents.routes.train`") from None
    return LearnedPrior(scorer, names)
