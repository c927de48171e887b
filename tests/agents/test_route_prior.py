"""The learned expansion prior (agents.routes.policy): a short imitation of known routes ranks the right template
far above chance on held-out targets, steers MCTS to fewer expansions than a uniform prior, and a prior for
other templates is refused with the reason."""

import json

import pytest
import torch

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.mcts import mcts
from agents.routes.policy import LearnedPrior, examples, load_prior, save_prior, train_prior
from agents.routes.targets import target_set
from agents.routes.train import accuracy

TEMPLATES, STOCK = template_file.load(), stock_file.load()
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    scorer = train_prior(TEMPLATES, examples(target_set(TEMPLATES, STOCK, 120)), epochs=20)
    path = tmp_path_factory.mktemp("prior") / "prior"
    save_prior(scorer, TEMPLATES, path)
    return path


def test_the_prior_ranks_the_right_template_far_above_chance(trained):
    prior = load_prior(trained, TEMPLATES)
    top1, top5 = accuracy(prior, examples(target_set(TEMPLATES, STOCK, 24, held_out=True)))
    assert top1 > 0.3 and top5 > 0.6  # chance: 1/49 and 5/49


def test_guided_mcts_needs_fewer_expansions_than_uniform(trained):
    prior = load_prior(trained, TEMPLATES)
    held = target_set(TEMPLATES, STOCK, 6, depths=range(2, 5), held_out=True)
    shared: dict = {}  # a molecule expanded once for both searches (each still counts its own expansions)
    uniform = [mcts(t.smiles, TEMPLATES, STOCK, max_expansions=120, shared=shared) for t in held]
    guided = [mcts(t.smiles, TEMPLATES, STOCK, prior=prior, max_expansions=120, shared=shared) for t in held]
    assert sum(r.route is not None for r in guided) >= sum(r.route is not None for r in uniform)
    assert sum(r.expansions for r in guided) < sum(r.expansions for r in uniform)


def test_a_prior_for_other_templates_is_refused(trained, tmp_path):
    meta = json.loads(trained.with_suffix(".json").read_text())
    meta["templates"] = meta["templates"][:-1]
    other = tmp_path / "other"
    other.with_suffix(".json").write_text(json.dumps(meta))
    other.with_suffix(".pt").write_bytes(trained.with_suffix(".pt").read_bytes())
    with pytest.raises(ValueError, match="trained on other templates: it does not know"):
        load_prior(other, TEMPLATES)
    with pytest.raises(FileNotFoundError, match="train one with"):
        load_prior(tmp_path / "nowhere", TEMPLATES)


def test_the_shipped_prior_loads_and_says_how_it_was_trained():
    from pathlib import Path

    path = Path(template_file.__file__).resolve().parents[1] / "policies" / "route_prior"
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["command"].startswith("python -m agents.routes.train") and meta["held_out_top5"] > 0.8
    assert isinstance(load_prior(path, TEMPLATES), LearnedPrior)


def test_a_prior_that_would_unpack_to_gigabytes_is_refused_before_it_is_read(trained, tmp_path):
    import zipfile

    from agents.routes import policy

    bomb = tmp_path / "bomb"
    bomb.with_suffix(".json").write_text(trained.with_suffix(".json").read_text())
    zeros = bytes(2**20)
    with zipfile.ZipFile(bomb.with_suffix(".pt"), "w", zipfile.ZIP_DEFLATED) as zout:
        with zout.open("bomb/data/0", "w", force_zip64=True) as big:  # a few hundred kB on disk
            for _ in range(policy.MAX_WEIGHTS_BYTES // len(zeros) + 1):
                big.write(zeros)
    with pytest.raises(ValueError, match=r"bomb\.pt: would unpack to 257 MB, more than a route prior does"):
        load_prior(bomb, TEMPLATES)
