"""`twin route`: a synthesis route to a molecule, from the route planners installed (``labtwin.routes``)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from twin.cli.common import (_fail, app, bar_progress, bench_app, console, err, machine_output, narrow_table,
                             print_table, writable)
from twin.cli.stopping import exit_status, interruptible, part_done, sigterm_unwinds, stopped_by, stopped_partway
from twin.core.counts import counted
from twin.core import plugins
from twin.core.errors import TwinError


@app.command()
def route(
    smiles: Annotated[str, typer.Argument(help="the target molecule as SMILES, e.g. aspirin: CC(=O)OC1=CC=CC=C1C(=O)O")],
    method: Annotated[str, typer.Option(help="mcts (guided by the learned prior), breadth-first or random")] = "mcts",
    stock: Annotated[Optional[Path], typer.Option(help="a stock file (smiles[,name,eur_per_g]); default: the shipped one")] = None,
    templates: Annotated[Optional[Path], typer.Option(help="a template file; default: the shipped one")] = None,
    prior: Annotated[Optional[str], typer.Option("--prior", "--policy", help="mcts: a route prior (P for P.pt + "
                                                 "P.json, as `twin train --agent route` writes), or none (uniform)")] = None,
    seconds: Annotated[float, typer.Option(help="search budget, wall seconds")] = 10.0,
    as_json: Annotated[bool, typer.Option("--json", help="print the route as JSON")] = False,
    save: Annotated[Optional[Path], typer.Option(help="also draw the route (RDKit) into this .svg or .png file")] = None,
) -> None:
    """A route to SMILES from the stock: its steps in the order the lab runs them, what it buys, estimates.
    Exit 0: a route (or the target is in stock); 1: no route within the budget; 2: bad input."""
    writable("--save", save)
    try:
        planner = plugins.load("routes", method)
    except TwinError as exc:
        _fail(exc)
    try:
        started = time.perf_counter()
        if not 0 < seconds < math.inf:
            raise ValueError(f"--seconds {seconds:g}: give the search a budget above 0, in wall seconds (e.g. 10)")
        if save is not None and save.suffix.lower() not in (".svg", ".png"):
            raise ValueError(f"--save {save}: a route is drawn as SVG or PNG; give a file name ending in .svg or .png")
        shown = smiles if len(smiles) <= 60 else smiles[:57] + "…"
        with sigterm_unwinds(redeliver=True):  # before the line that says Ctrl-C (or SIGTERM) stops it
            err.print(f"searching for a route to {shown} ({method}, up to {seconds:g} s; Ctrl-C stops it) …",
                      highlight=False)
            data = planner(smiles, stock=stock, templates=templates, prior=prior, seconds=seconds,
                           **({"save": save} if save is not None else {}))
    except (ValueError, FileNotFoundError) as exc:
        _fail(TwinError(str(exc)))
    except KeyboardInterrupt as stop:  # was a silent exit 130
        err.print(f"{stopped_by(stop)} after {time.perf_counter() - started:.1f} s of the search, before it found a "
                  f"route: nothing shown{' or drawn' if save is not None else ''}; --seconds sets how long it "
                  "searches before it gives up by itself", highlight=False)
        raise typer.Exit(exit_status(stop)) from None
    if as_json:
        console.print_json(json.dumps(data))
    else:
        _show(data, method)
        if save is not None and data["solved"]:
            console.print(f"drawn: {save}", highlight=False)
    if not data["solved"]:
        raise typer.Exit(1)


def _what_next(data: dict) -> str:
    """What a person can change when no route was found: the budget, or what the search starts from."""
    if data["why"].startswith("stopped after") and data["why"].endswith(" s"):
        return f"give it longer (--seconds {2 * max(data['seconds'], 1):.0f}), or another --method"
    if data["why"].startswith("stopped after"):  # its expansions: as many as a search makes
        return "try another --method (mcts with the shipped --prior expands the fewest molecules)"
    if data["expansions"] <= 1:  # the target itself: not one template's product matches it
        return ("no template makes this molecule: give --templates a file with one that does, or --stock one that "
                "holds it (docs/routes.md)")
    return "give --stock the building blocks it lacks, or --templates more reactions (docs/routes.md)"


def _show(data: dict, method: str) -> None:
    searched = f"{method}, {data['expansions']} expansions, {data['seconds']:.2f} s"
    if not data["solved"]:
        console.print(f"no route to {data['target']} ({searched}): {data['why']}; {_what_next(data)}",
                      highlight=False)
        return
    if not data["steps"]:
        console.print(f"{data['target']}: {data['why'] or 'in stock'}; nothing to make", highlight=False)
        return
    names = {b["smiles"]: b["name"] for b in data["bought"]}
    made = {s["product"]: f"({s['step']})" for s in data["steps"]}
    table = Table(title=f"{data['target']}: {len(data['steps'])} steps, depth {data['depth']} ({searched})",
                  title_justify="left")
    for h in ("#", "reaction", "from", "yield %", "hours"):
        table.add_column(h)
    for s in data["steps"]:
        table.add_row(str(s["step"]), s["reaction"], " + ".join(names.get(r) or made.get(r) or r for r in s["reactants"]),
                      "{:.0f}–{:.0f}".format(*s["yield_pct"]), "{:g}–{:g}".format(*s["hours"]))
    print_table(table)
    prices = ", ".join(f"{b['name']} ({b['eur_per_g']:g} €/g)" if b["eur_per_g"] is not None else b["name"]
                       for b in data["bought"])
    console.print(f"buys: {prices}", highlight=False)
    cost = f"; stock {data['stock_eur_per_g']:g} € for 1 g of each" if data["stock_eur_per_g"] is not None else ""
    console.print(f"estimates: {data['hours'][0]:g}–{data['hours'][1]:g} h of reactions in series, overall yield "
                  f"≈ {data['overall_yield_pct']:g} % (mean yields multiplied){cost}", highlight=False)


@bench_app.command("routes")
@interruptible
def bench_routes(
    targets: Annotated[int, typer.Option(help="how many targets of the set")] = 100,
    target_set: Annotated[str, typer.Option("--set", help="held-out (made forwards from the stock, depths 1–6) "
                                                         "or drugs (named drugs)")] = "held-out",
    methods: Annotated[Optional[str], typer.Option(help="comma-separated route planners; mcts:none is MCTS "
                                                        "with a uniform prior, mcts:P with prior P; default: all, "
                                                        "and mcts:none")] = None,
    seconds: Annotated[float, typer.Option(help="search budget per target, wall seconds")] = 10.0,
    workers: Annotated[int, typer.Option(min=1, help="searches run in parallel")] = 2,
    as_json: Annotated[bool, typer.Option("--json", help="print the rows and every search's result as JSON")] = False,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write every search's result to this CSV file")] = None,
) -> None:
    """Solved rate, route length against the known one, expansions and time per target, for every search method."""
    writable("--csv", csv_out)
    from twin.tools.route_bench import CAPTION, HEADER, bench, default_methods, rows, split
    from twin.tools.route_bench import targets as make_targets

    try:
        if targets < 1 or seconds <= 0:
            raise TwinError(f"--targets {targets} --seconds {seconds:g}: give at least 1 target and a positive budget")
        names = [m.strip() for m in methods.split(",") if m.strip()] if methods else default_methods()
        for m in names:
            plugins.load("routes", split(m)[0])
        chosen = make_targets(target_set, targets)
    except TwinError as exc:
        _fail(exc)
    progress = bar_progress(as_json)
    cut = None
    with progress:
        bar = progress.add_task(f"{len(names)} methods × {len(chosen)} targets", total=len(names) * len(chosen))
        try:
            results = bench(names, chosen, seconds, workers, on_done=lambda r: progress.advance(bar))
        except (ValueError, FileNotFoundError) as exc:
            _fail(TwinError(str(exc)))
        except KeyboardInterrupt as stop:  # the targets every method finished still make a table
            results, cut, csv_out = part_done(stop, as_json), stop, None  # a table, and no file of a part
    table_rows = rows(results, names)
    if machine_output(as_json, csv_out, list(HEADER), table_rows, results, target_set=target_set, seconds=seconds):
        return
    done = len({r["smiles"] for r in results})
    table = narrow_table(list(HEADER), f"{done if cut is None else f'{done} of {len(chosen)}'} {target_set} targets, "
                         f"{seconds:g} s each", CAPTION)
    for row in table_rows:
        table.add_row(*row)
    print_table(table)
    if cut is not None:
        stopped_partway(cut, f"the {counted(done, 'target', 'targets')} every method finished")
