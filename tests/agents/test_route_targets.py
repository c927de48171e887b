"""Targets made forwards from the stock (agents.routes.targets): each comes with a route that replays, of the
length asked, from stock; training and held-out sets never share a target; the search finds short ones."""

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.search import breadth_first
from agents.routes.targets import target_set
from agents.routes.templates import forward

TEMPLATES, STOCK = template_file.load(), stock_file.load()
BY_NAME = {t.name: t for t in TEMPLATES}


def test_each_target_comes_with_a_route_of_its_length_that_replays_from_stock():
    targets = target_set(TEMPLATES, STOCK, 12, depths=range(1, 5), held_out=True)
    assert [t.steps for t in targets] == [1, 2, 3, 4] * 3
    for target in targets:
        assert len(target.route) == target.steps and target.route[-1][2] == target.smiles
        made: set[str] = set()
        for name, reactants, product in target.route:
            assert all(r in STOCK or r in made for r in reactants)
            assert product in forward(BY_NAME[name], reactants) and product not in STOCK
            made.add(product)


def test_training_and_held_out_targets_differ_and_repeat_by_seed():
    train = target_set(TEMPLATES, STOCK, 10)
    held = target_set(TEMPLATES, STOCK, 10, held_out=True)
    assert not {t.smiles for t in train} & {t.smiles for t in held}
    assert [t.smiles for t in target_set(TEMPLATES, STOCK, 10)] == [t.smiles for t in train]


def test_the_search_finds_routes_no_longer_than_the_ones_targets_were_made_by():
    for target in target_set(TEMPLATES, STOCK, 6, depths=range(1, 3), held_out=True):
        route = breadth_first(target.smiles, TEMPLATES, STOCK, max_seconds=20).route
        assert route is not None and route.depth <= target.steps
