"""Route planners as the kernel loads them (entry points ``labtwin.routes``): ``plan(target, stock=None,
templates=None, prior=None, seconds=10.0)`` → the route as plain data (``summary``: JSON-able, what `twin route`
prints). ``stock`` and ``templates`` are
files (default: the shipped ones); ``prior`` (MCTS only) a route prior (default: the shipped one; ``"none"``:
uniform); ``save`` an .svg or .png file to draw a route found into. Bad input raises ``ValueError`` (a SMILES RDKit cannot read, a broken file) or ``FileNotFoundError``.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

from agents.routes import stock as stock_file
from agents.routes import templates as template_file
from agents.routes.mcts import mcts, random_search, uniform
from agents.routes.policy import load_prior
from agents.routes.search import Result, breadth_first

SHIPPED_PRIOR = Path(__file__).resolve().parents[1] / "policies" / "route_prior"


def draw(data: dict, path: Path) -> None:
    """The route as an SVG or PNG grid drawn by RDKit: a row per step — what it takes (bought, or made by an earlier
    step), then what it makes — in the order the lab runs them."""
    from rdkit import Chem
    from rdkit.Chem import Draw

    kind = Path(path).suffix.lower()
    if kind not in (".svg", ".png"):
        raise ValueError(f"{path}: a route is drawn as SVG or PNG; give a file name ending in .svg or .png")
    names = {b["smiles"]: b["name"] for b in data.get("bought", [])}
    made = {s["product"]: s["step"] for s in data.get("steps", [])}
    width = max([len(s["reactants"]) for s in data.get("steps", [])] or [0]) + 1
    mols, legends = [], []
    for s in data.get("steps", []):
        row = [(r, f"{names[r]}" if r in names else f"from step {made.get(r, '?')}") for r in s["reactants"]]
        row += [("", "")] * (width - 1 - len(row)) + [(s["product"], f"step {s['step']}: {s['reaction']}"[:48])]
        for smiles, legend in row:
            mols.append(Chem.MolFromSmiles(smiles) if smiles else Chem.Mol())
            legends.append(legend)
    if not mols:  # the target is in stock
        mols, legends = [Chem.MolFromSmiles(data["target"])], ["in stock"]
    if kind == ".png":
        image = Draw.MolsToGridImage(mols, molsPerRow=max(width, 1), subImgSize=(260, 200), legends=legends)
        image.save(path, format="PNG")
        return
    svg = Draw.MolsToGridImage(mols, molsPerRow=max(width, 1), subImgSize=(260, 200), legends=legends, useSVG=True)
    # RDKit draws the legends as glyph outlines: the route in words too, for search, screen readers and tests
    words = "; ".join(f"step {s['step']}: {s['reaction']}: "
                      f"{' + '.join(names.get(r) or f'from step {made.get(r)}' for r in s['reactants'])} -> {s['product']}"
                      for s in data.get("steps", [])) or "in stock"
    head = svg.index(">", svg.index("<svg")) + 1
    svg = (svg[:head] + f"<title>route to {escape(data['target'])}</title><desc>{escape(words)}</desc>" + svg[head:])
    Path(path).write_text(svg)


def inputs(stock: str | Path | None = None, templates: str | Path | None = None):
    return (template_file.load(Path(templates) if templates else template_file.TEMPLATES),
            stock_file.load(Path(stock) if stock else stock_file.STOCK))


METHODS = ("mcts", "breadth-first", "random")


def search(method: str, target: str, templates, stock, prior=None, seconds: float = 10.0,
           avoid: frozenset[tuple[str, str]] = frozenset()) -> Result:
    """One search by name (``METHODS``); ``prior`` as for ``plan_mcts`` (a path, None: the shipped one,
    "none": uniform), loaded only for MCTS."""
    if method == "mcts":
        weights = uniform if prior == "none" else load_prior(Path(prior) if prior else SHIPPED_PRIOR, templates)
        return mcts(target, templates, stock, prior=weights, max_seconds=seconds, avoid=avoid)
    if method == "breadth-first":
        return breadth_first(target, templates, stock, max_seconds=seconds, avoid=avoid)
    if method == "random":
        return random_search(target, templates, stock, max_seconds=seconds, avoid=avoid)
    raise ValueError(f"unknown route search {method!r}: use one of {', '.join(METHODS)}")


def plan_mcts(target: str, stock=None, templates=None, prior=None, seconds: float = 10.0,
              save: Path | None = None) -> dict:
    return _saved(summary(search("mcts", target, *inputs(stock, templates), prior, seconds)), save)


def plan_breadth_first(target: str, stock=None, templates=None, prior=None, seconds: float = 10.0,
                       save: Path | None = None) -> dict:
    return _saved(summary(search("breadth-first", target, *inputs(stock, templates), prior, seconds)), save)


def plan_random(target: str, stock=None, templates=None, prior=None, seconds: float = 10.0,
                save: Path | None = None) -> dict:
    return _saved(summary(search("random", target, *inputs(stock, templates), prior, seconds)), save)


def _saved(data: dict, save: Path | None) -> dict:
    if save is not None and data["solved"]:
        draw(data, save)
    return data


def summary(result: Result) -> dict:
    """A route as plain data: its steps in the order the lab runs them, the stock it buys, and estimates."""
    route = result.route
    out: dict = {"target": result.target, "solved": route is not None, "expansions": result.expansions,
                 "seconds": round(result.seconds, 3), "why": result.why}
    if route is None:
        return out
    steps = []
    for n, r in enumerate(route.order(), 1):
        steps.append({"step": n, "reaction": r.template.name, "class": r.template.reaction_class,
                      "reactants": list(r.reactants), "product": r.product,
                      "yield_pct": list(r.template.yield_pct), "hours": list(r.template.hours),
                      "conditions": r.template.conditions})
    bought = []
    for m in route.bought():
        item = route.stock.get(m)
        bought.append({"smiles": m, "name": item.name if item else m, "eur_per_g": item.eur_per_g if item else None})
    mean = lambda lo_hi: (lo_hi[0] + lo_hi[1]) / 2  # noqa: E731
    overall = 1.0
    for r in route.order():
        overall *= mean(r.template.yield_pct) / 100
    prices = [b["eur_per_g"] for b in bought]
    out.update(steps=steps, bought=bought, depth=route.depth,
               hours=[sum(r.template.hours[0] for r in route.order()), sum(r.template.hours[1] for r in route.order())],
               overall_yield_pct=round(100 * overall, 1),
               stock_eur_per_g=None if None in prices else round(sum(prices), 2))
    return out
