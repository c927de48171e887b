"""The route panel of a synthesis campaign: the route drawn by RDKit (a row per reaction, redrawn when the
planner switches to an alternative), and a table of which step is waiting,
running where, done with how much product, or failed — from the route planner's experiments (their params
carry ``reaction``, ``step``, ``route``; the first of each route also its whole ``plan``)."""

from __future__ import annotations

from typing import Any

from twin.view.molecules import route_png


class RouteView:
    def __init__(self, canvas: Any) -> None:
        self.c = canvas
        self.steps: dict[int, dict[str, Any]] = {}  # experiment -> its row
        self.route = 0

    def proposed(self, t: float, experiment: int, params: dict[str, Any]) -> None:
        route = _int(params.get("route"))
        plan = params.get("plan")
        if isinstance(plan, list) and route != self.route:
            self.route = route
            png = route_png(tuple(str(r) for r in plan))
            if png is not None:
                self.c.image("route/plan", t, png)
        self.steps[experiment] = {"route": route, "step": _int(params.get("step")), "steps": _int(params.get("steps")),
                                  "template": str(params.get("template", "?"))[:80], "state": "waiting"}
        self._table(t)

    def running(self, t: float, experiment: int | None, device: str | None) -> None:
        row = self.steps.get(experiment) if experiment is not None else None
        if row is not None:
            row["state"] = f"running on {device}"
            self._table(t)

    def finished(self, t: float, experiment: int | None, outputs: dict[str, Any] | None, reason: str = "") -> None:
        row = self.steps.get(experiment) if experiment is not None else None
        if row is None:
            return
        if outputs is None:
            row["state"] = f"abandoned: {reason[:80]}"
        elif not outputs.get("identity"):
            row["state"] = "failed: no product found"
        else:
            row["state"] = (f"done: {outputs.get('product_mg', 0):.0f} mg at {outputs.get('purity_pct', 0):.1f} %, "
                            f"yield {outputs.get('yield_pct', 0):.0f} %")
        self._table(t)

    def _table(self, t: float) -> None:
        lines = ["| exp | route | step | reaction | state |", "|---|---|---|---|---|"]
        lines += [f"| {e} | {r['route']} | {r['step']}/{r['steps']} | {r['template']} | {r['state']} |"
                  for e, r in sorted(self.steps.items())]
        self.c.document("route/steps", "\n".join(lines), t)


def _int(x: Any) -> int:
    return int(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else 0
