"""`twin bench routes`: every route search method on a set of targets whose route length is known.

Methods are the installed route planners (``labtwin.routes``), ``NAME:PRIOR`` for MCTS with another prior
(``mcts:none``: uniform); target sets are ``labtwin.route_targets`` functions ``(count) -> [{name, smiles,
steps}]``. Each (method, target) is one search with the same wall-time budget, in parallel processes.
"""

from __future__ import annotations

import statistics
from typing import Any, Callable

from twin.core import plugins
from twin.core.errors import PluginError
from twin.tools.pool import WorkerPool, keep_done

HEADER = ("method", "solved %", "≤known+1 %", "exp. mean", "exp. med", "s med", "s max")
CAPTION = ("solved: a route within the budget; ≤known+1: of those solved, the share no longer than the target's "
           "known route plus one step; exp.: expansions (one molecule, every template backwards); s: wall seconds "
           "per search")


def default_methods() -> list[str]:
    names = sorted(plugins.installed("routes"))
    return [m for n in names for m in ([n, f"{n}:none"] if n == "mcts" else [n])]


def split(method: str) -> tuple[str, str | None]:
    """``mcts:none`` -> (``mcts``, ``none``); a name alone has no prior."""
    name, _, prior = method.partition(":")
    return name, prior or None


def targets(target_set: str, count: int) -> list[dict[str, Any]]:
    made = plugins.load("route_targets", target_set)(count)
    for i, t in enumerate(made):
        if not isinstance(t, dict) or not isinstance(t.get("smiles"), str):
            raise PluginError(f"route target set {target_set!r}: item {i} is not {{name, smiles, steps}}: {t!r:.80}")
    return made[:count]


def _one(job: tuple[str, dict[str, Any], float]) -> dict[str, Any]:
    method, target, seconds = job
    name, prior = split(method)
    data = plugins.load("routes", name)(target["smiles"], prior=prior, seconds=seconds)
    return {"method": method, "target": target.get("name", target["smiles"]), "smiles": target["smiles"],
            "known": target.get("steps"), "solved": bool(data.get("solved")),
            "steps": len(data.get("steps", [])) if data.get("solved") else None,
            "expansions": int(data.get("expansions", 0)), "seconds": float(data.get("seconds", 0.0))}


def bench(methods: list[str], chosen: list[dict[str, Any]], seconds: float, workers: int,
          on_done: Callable[[dict[str, Any]], None] = lambda r: None) -> list[dict[str, Any]]:
    jobs = [(m, t, seconds) for t in chosen for m in methods]  # target by target, every method in each
    results: list[dict[str, Any]] = []
    order = {m: i for i, m in enumerate(methods)}
    with WorkerPool(workers) as pool:  # one thread each, torch's too (OMP_NUM_THREADS)
        try:
            for fut in pool.completed([pool.submit(_one, job) for job in jobs]):
                results.append(fut.result())
                on_done(results[-1])
        except KeyboardInterrupt as stop:  # the targets every method finished are kept for the table
            runs = {(r["method"], r["smiles"]) for r in results}
            whole = {t["smiles"] for t in chosen if all((m, t["smiles"]) in runs for m in methods)}
            keep_done(stop, sorted((r for r in results if r["smiles"] in whole),
                                   key=lambda r: (order[r["method"]], r["target"])))
            raise
    return sorted(results, key=lambda r: (order[r["method"]], r["target"]))


def rows(results: list[dict[str, Any]], methods: list[str]) -> list[list[str]]:
    out = []
    for m in methods:
        mine = [r for r in results if r["method"] == m]
        if not mine:
            continue
        solved = [r for r in mine if r["solved"]]
        known = [r for r in solved if r["known"] is not None]
        near = f"{100 * sum(r['steps'] <= r['known'] + 1 for r in known) / len(known):.0f}" if known else "–"
        out.append([m, f"{100 * len(solved) / len(mine):.0f}", near,
                    f"{statistics.mean(r['expansions'] for r in mine):.1f}",
                    f"{statistics.median(r['expansions'] for r in mine):.0f}",
                    f"{statistics.median(r['seconds'] for r in mine):.2f}", f"{max(r['seconds'] for r in mine):.1f}"])
    return out
