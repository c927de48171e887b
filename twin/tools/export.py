"""``twin export``: a run's journal as tables people analyse — CSV, Parquet (pyarrow) or JSON lines.

One file per table, in a directory:

- ``experiments``: one row per proposed experiment, as the journal's ``experiments`` table has it, its JSON
  columns spread out (``param.<name>``, ``output.<name>``, ``score.<target>``; a nested value stays JSON text);
- ``attempts``: one row per attempt of a step: device, when it was sent, accepted and ended (lab times), its
  deadline (``deadline_s``: lab seconds after it was sent, as the command said), how it ended;
- ``devices``: one row per device: type, attempts, failures, busy share;
- ``consumables``: each item's level over time: its start, every step that used some, every refill;
- ``decisions``: every state change the campaign journalled (``detail`` as JSON text);
- ``operator``: every act of an operator (who, what, when, why, and a refusal's reason);
- ``provenance.json`` beside them: the run's provenance record with the operators' acts.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

from twin.campaign.journal_read import no_such_journal, read_events, read_experiments, read_run
from twin.core.errors import TwinError
from twin.core.printable import inert
from twin.core.whole_files import written_whole
from twin.scenario.model import instance_names

WHAT = ("experiments", "attempts", "devices", "consumables", "decisions", "operator")
FORMATS = ("csv", "parquet", "jsonl")
# each table's columns, written even when it has no rows (a run without consumables, without an operator), so that
# a script reading `item` or `act` finds the column; experiments add param.*, output.* and score.* after theirs
COLUMNS = {"experiments": ("experiment", "status", "reason", "attempts", "retries", "degraded", "t_proposed_s",
                           "t_done_s", "route"),
           "attempts": ("task", "experiment", "attempt", "device", "t_sent_s", "deadline_s", "t_accepted_s", "t_end_s",
                        "outcome", "code", "reason"),
           "devices": ("device", "type", "attempts", "failed", "done", "busy_share"),
           "consumables": ("t_lab_s", "item", "unit", "level", "change", "why", "task", "who"),
           "decisions": ("seq", "t_lab_s", "kind", "experiment", "task", "attempt", "device", "detail"),
           "operator": ("t_lab_s", "act", "who", "experiment", "now", "reason", "refused")}
_ENDS = {"attempt.done": "done", "attempt.failed": "failed", "attempt.cancelled": "cancelled"}


def export(journal: str | Path, out: str | Path, fmt: str = "csv", what: list[str] | None = None) -> list[Path]:
    """Write the tables ``what`` (default: all) of the run in ``journal`` to the directory ``out``; returns the
    files written."""
    path = Path(journal)
    if not path.is_file():
        raise no_such_journal(path)
    if fmt not in FORMATS:
        raise TwinError(f"--format {fmt!r}: use one of {', '.join(FORMATS)}")
    chosen = list(what or WHAT)
    unknown = [w for w in chosen if w not in WHAT]
    if unknown:
        raise TwinError(f"--what {','.join(unknown)}: the tables are {', '.join(WHAT)}")
    run, events, experiments = read_run(path, needs=("scenario",)), read_events(path), read_experiments(path)
    tables = {"experiments": lambda: experiment_rows(experiments), "attempts": lambda: attempt_rows(events),
              "devices": lambda: device_rows(run, events), "consumables": lambda: consumable_rows(run, events),
              "decisions": lambda: decision_rows(events),
              "operator": lambda: operator_rows(events)}
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TwinError(f"--out {out}: cannot make the directory ({exc.strerror}: {exc.filename}); give --out a "
                        "directory you can write") from None
    written = [_write(out / f"{name}.{fmt}", tables[name](), fmt, COLUMNS[name]) for name in chosen]
    record = {**(run.get("provenance") or _older(run)), "operator_acts": operator_rows(events),
              "summary": run.get("summary"), "journal": str(path)}
    with written_whole(out / "provenance.json") as partial:
        partial.write_text(json.dumps(record, indent=2, default=str) + "\n")
    return [*written, out / "provenance.json"]


def _older(run: dict[str, Any]) -> dict[str, Any]:
    """A journal written before provenance was: what can be told from its scenario."""
    from twin.runtime.run_record import scenario_hash
    from twin.scenario import parse

    s = parse(run["scenario"], "the journal's scenario")
    return {"scenario": s.name, "scenario_sha256": scenario_hash(s), "seed": s.campaign.seed,
            "note": "this journal was written before runs recorded their provenance: versions and files unknown"}


def _json(text: str | None) -> Any:
    return json.loads(text) if text else None


def _flat(value: Any) -> Any:
    """A cell: numbers, text, booleans and nulls as they are; anything nested as JSON text."""
    return value if value is None or isinstance(value, (int, float, str, bool)) else json.dumps(value, sort_keys=True)


def experiment_rows(experiments: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for e in experiments:
        row: dict[str, Any] = {"experiment": e["id"], "status": e["status"], "reason": e["reason"],
                               "attempts": e["attempts"], "retries": e["retries"], "degraded": bool(e["degraded"]),
                               "t_proposed_s": e["t_proposed"], "t_done_s": e["t_done"],
                               "route": " > ".join(f"{s[0]}@{s[1]}" for s in _json(e["route"]) or [])}
        for prefix, column in (("param", "params"), ("output", "outputs"), ("score", "scores")):
            for k, v in (_json(e[column]) or {}).items():
                row[f"{prefix}.{k}"] = _flat(v)
        rows.append(row)
    return rows


def attempt_rows(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows: dict[tuple[str, int], dict[str, Any]] = {}
    for e in events:
        kind, key = e["kind"], (e["task"], e["attempt"])
        if kind == "attempt.dispatched":
            detail = _json(e["detail"]) or {}
            rows[key] = {"task": e["task"], "experiment": e["experiment"], "attempt": e["attempt"],
                         "device": e["device"], "t_sent_s": e["t_lab"], "deadline_s": detail.get("deadline_s"),
                         "t_accepted_s": None, "t_end_s": None, "outcome": "in the lab", "code": None, "reason": None}
        elif key in rows and kind == "attempt.running":
            rows[key]["t_accepted_s"] = e["t_lab"]
        elif key in rows and kind in _ENDS and rows[key]["t_end_s"] is None:
            detail = _json(e["detail"])
            row = rows[key]
            row.update(t_end_s=e["t_lab"], outcome=_ENDS[kind])
            if isinstance(detail, dict):
                row.update(code=detail.get("code"), reason=detail.get("reason"))
            elif detail is not None:
                row["reason"] = str(detail)
    return list(rows.values())


def device_rows(run: dict[str, Any], events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    from twin.scenario import parse

    s, summary = parse(run["scenario"], "the journal's scenario"), run.get("summary") or {}
    types = {name: dtype for dtype in s.devices for name in s.instance_names(dtype)}
    counts: dict[str, dict[str, int]] = {name: {"attempts": 0, "failed": 0, "done": 0} for name in types}
    for e in events:
        dev = counts.get(e["device"] or "")
        if dev is not None and e["kind"] in ("attempt.dispatched", "attempt.failed", "attempt.done"):
            dev[{"attempt.dispatched": "attempts", "attempt.failed": "failed", "attempt.done": "done"}[e["kind"]]] += 1
    busy = summary.get("utilisation") or {}
    return [{"device": name, "type": dtype, **counts[name], "busy_share": busy.get(name)}
            for name, dtype in types.items()]


def consumable_rows(run: dict[str, Any], events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    scenario = run.get("scenario") or {}
    stocks = scenario.get("consumables") or {}
    rows = [{"t_lab_s": 0.0, "item": stock, "unit": c.get("unit", ""), "level": c["level"], "change": None,
             "why": "start", "task": None, "who": None}
            for name, c in stocks.items() for stock in _stocks_of(name, c, scenario.get("devices") or {})]
    for e in events:
        d = _json(e["detail"]) if e["kind"] in ("attempt.dispatched", "consumable.refilled",
                                                 "consumable.returned") else None
        if e["kind"] == "attempt.dispatched" and isinstance(d, dict):
            for item, used in (d.get("used") or {}).items():
                unit = stocks.get(item.split("@")[0], {}).get("unit", "")
                rows.append({"t_lab_s": e["t_lab"], "item": item, "unit": unit,
                             "level": d["left"][item], "change": -used, "why": "used", "task": e["task"],
                             "who": e["device"]})
        elif e["kind"] == "consumable.refilled" and isinstance(d, dict):
            rows.append({"t_lab_s": e["t_lab"], "item": d["item"], "unit": d.get("unit", ""), "level": d["level"],
                         "change": d["amount"], "why": "refilled", "task": None, "who": d.get("who")})
        elif e["kind"] == "consumable.returned" and isinstance(d, dict):
            rows.append({"t_lab_s": e["t_lab"], "item": d["item"], "unit": d.get("unit", ""), "level": d["level"],
                         "change": d["amount"], "why": "returned (refused before it began)", "task": e["task"],
                         "who": e["device"]})
    return rows


def _stocks_of(item: str, spec: dict[str, Any], devices: dict[str, Any]) -> list[str]:
    """The stocks of ``item``: the lab's one, or one per instance of the device type that holds it."""
    holder = spec.get("device")
    if not holder or holder not in devices:
        return [item]
    return [f"{item}@{name}" for name in instance_names(holder, int(devices[holder].get("instances", 1)))]


def decision_rows(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{"seq": e["seq"], "t_lab_s": e["t_lab"], "kind": e["kind"], "experiment": e["experiment"],
             "task": e["task"], "attempt": e["attempt"], "device": e["device"], "detail": e["detail"]}
            for e in events if not e["kind"].startswith("msg.")]


def operator_rows(events: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rows = []
    for e in events:
        if e["kind"].startswith("operator."):
            d = _json(e["detail"]) or {}
            refused = e["kind"] == "operator.refused"
            rows.append({"t_lab_s": e["t_lab"], "act": d.get("command") if refused else e["kind"].split(".", 1)[1],
                         "who": d.get("who"), "experiment": e["experiment"], "now": bool(d.get("now", False)),
                         "reason": d.get("reason", ""), "refused": d.get("why") if refused else None})
    return rows


def _columns(rows: list[dict[str, Any]], base: tuple[str, ...] = ()) -> list[str]:
    cols: dict[str, None] = dict.fromkeys(base)
    for r in rows:
        cols.update(dict.fromkeys(r))
    return list(cols)


def _write(path: Path, rows: list[dict[str, Any]], fmt: str, base: tuple[str, ...] = ()) -> Path:
    with written_whole(path) as partial:
        _write_table(partial, rows, fmt, base)
    return path


def _write_table(path: Path, rows: list[dict[str, Any]], fmt: str, base: tuple[str, ...] = ()) -> None:
    cols = _columns(rows, base)
    if fmt == "csv":
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=cols)
            w.writeheader()
            w.writerows({k: inert(v) for k, v in r.items()} for r in rows)
    elif fmt == "jsonl":
        with open(path, "w") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    else:
        import pyarrow as pa
        import pyarrow.parquet as pq

        data = {c: [r.get(c) for r in rows] for c in cols}
        arrays = {}
        for c, values in data.items():
            try:
                arrays[c] = pa.array(values)
            except (pa.ArrowInvalid, pa.ArrowTypeError):  # a column of mixed kinds: kept as text
                arrays[c] = pa.array([None if v is None else str(v) for v in values], pa.string())
        pq.write_table(pa.table(arrays) if arrays else pa.table({}), path)
