"""Breadth-first retrosynthesis (agents.routes.search): named drugs from the shipped stock, shortest routes
first, routes the lab can run in order, and a clear answer when there is nothing to do or no route."""

import pytest

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.search import breadth_first
from agents.routes.targets import NAMED
from agents.routes.templates import canonical, forward

TEMPLATES, STOCK = template_file.load(), stock_file.load()


@pytest.mark.parametrize("name,smiles,steps", NAMED)
def test_named_drugs_have_routes_from_the_stock_that_run_in_order(name, smiles, steps):
    result = breadth_first(smiles, TEMPLATES, STOCK)
    route = result.route
    assert route is not None and route.steps == steps, result.why
    have = set(route.bought())
    assert all(m in STOCK for m in have)
    for reaction in route.order():  # each reaction's reactants are bought or made before it, and it makes its product
        assert set(reaction.reactants) <= have
        assert reaction.product in forward(reaction.template, reaction.reactants)
        have.add(reaction.product)
    assert canonical(smiles) in have


def test_aspirin_comes_from_salicylic_acid_and_acetic_anhydride():
    route = breadth_first("CC(=O)Oc1ccccc1C(=O)O", TEMPLATES, STOCK).route
    (only,) = route.order()
    assert set(only.reactants) == {canonical("OC(=O)c1ccccc1O"), canonical("CC(=O)OC(C)=O")}


def test_the_shortest_route_is_found_first():
    # 4-aminobenzoic acid is in stock, so benzocaine is one esterification; without it (and without the nitro
    # ester) the route goes through the nitro ester: esterify 4-nitrobenzoic acid, then reduce — two steps
    gone = {canonical("Nc1ccc(C(=O)O)cc1"), canonical("CCOC(=O)c1ccc([N+](=O)[O-])cc1")}
    without = stock_file.parse("smiles\n" + "\n".join(s for s in STOCK.items if s not in gone), "fewer.csv")
    short = breadth_first("CCOC(=O)c1ccc(N)cc1", TEMPLATES, STOCK).route
    longer = breadth_first("CCOC(=O)c1ccc(N)cc1", TEMPLATES, without).route
    assert short.steps == 1 and longer.steps == 2 and longer.depth == 2
    assert {r.template.name for r in longer.order()} & {"nitro reduction"}


def test_a_target_in_stock_needs_no_route_and_an_unreachable_one_says_why():
    bought = breadth_first("OC(=O)c1ccccc1O", TEMPLATES, STOCK)
    assert bought.route.steps == 0 and bought.why == "the target is in stock" and bought.expansions == 0
    nothing = breadth_first("C1CC2CCC1C2", TEMPLATES, STOCK)  # norbornane: no template touches it
    assert nothing.route is None and "no route within 6 steps" in nothing.why
    tight = breadth_first("CCN(CC)CC(=O)Nc1c(C)cccc1C", TEMPLATES, STOCK, max_expansions=1)
    assert tight.route is None and tight.why == "stopped after 1 expansions"
    with pytest.raises(ValueError, match="not a valid SMILES: 'C1CC'"):
        breadth_first("C1CC", TEMPLATES, STOCK)


def test_mcts_and_random_search_find_the_named_routes():
    from agents.routes.mcts import mcts, random_search

    for search in (mcts, random_search):
        aspirin = search("CC(=O)Oc1ccccc1C(=O)O", TEMPLATES, STOCK).route
        lidocaine = search("CCN(CC)CC(=O)Nc1c(C)cccc1C", TEMPLATES, STOCK).route
        assert aspirin.steps == 1 and lidocaine is not None and lidocaine.steps <= 3, search.__name__
        assert all(m in STOCK for m in lidocaine.bought())


def test_the_expansion_prior_steers_mcts():
    from agents.routes.mcts import mcts

    def likes(name):
        return lambda molecule, reactions: [10.0 if r.template.name == name else 0.01 for r in reactions]

    for name in ("amide from acyl chloride", "amide coupling (acid + amine)"):
        route = mcts("CCN(CC)CC(=O)Nc1c(C)cccc1C", TEMPLATES, STOCK, prior=likes(name), extra=0).route
        assert name in {r.template.name for r in route.order()}, [r.template.name for r in route.order()]


def test_mcts_ends_when_its_tree_is_searched_to_the_end_not_when_its_time_is_up():
    """From a stock of ethanol alone, aspirin's tree of routes is finite: MCTS went round it for its whole budget
    (135,000 selections in 3 s) and said it had stopped for time, which `twin route` turns into "give it longer"."""
    from agents.routes.mcts import mcts
    from agents.routes.stock import Item, Stock

    ethanol = Stock({"CCO": Item("CCO", "ethanol", None)}, "a test's")
    first = breadth_first("CC(=O)Oc1ccccc1C(=O)O", TEMPLATES, ethanol)
    assert first.route is None and first.why.startswith("no route within 6 steps")  # the whole tree, searched
    found = mcts("CC(=O)Oc1ccccc1C(=O)O", TEMPLATES, ethanol, max_seconds=30)
    assert found.route is None and found.why.startswith("the tree was searched to the end"), found.why
    assert found.seconds < 10 and found.expansions <= first.expansions


def test_mcts_says_why_it_found_nothing():
    from agents.routes.mcts import mcts

    assert "no route within 6 steps from this stock" in mcts("C1CC2CCC1C2", TEMPLATES, STOCK).why
    assert mcts("OC(=O)c1ccccc1O", TEMPLATES, STOCK).why == "the target is in stock"
    tight = mcts("CCN(CC)CC(=O)Nc1c(C)cccc1C", TEMPLATES, STOCK, max_expansions=1)
    assert tight.route is None and tight.why == "stopped after 1 expansions"
