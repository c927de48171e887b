"""`twin whatif`: what a change to the lab (instances, durations, faults, scheduler, planner, budget) does to
lab-hours and cost to target, over paired seeds."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich import box
from rich.table import Table

from twin.cli.common import (_fail, app, bar_progress, console, paired_assignments, recording_file, say_ended_early,
                             writable)
from twin.cli.stopping import interruptible, part_done, stopped_partway
from twin.core.counts import counted
from twin.core.errors import TwinError
from twin.core.printable import inert


def _variants_table(head: list[str], table_rows: list[list[str]], axes: int, whole_values: int) -> Table:
    table = Table(box=box.SIMPLE_HEAD, collapse_padding=True, pad_edge=False)
    for i, h in enumerate(head):
        # a varied field's name and values (up to ``whole_values`` wide) and the busiest type's name stay whole:
        # "reactor" over "92%", never squeezed away
        whole = [h] if i < axes else [row[i] for row in table_rows] if h == "busiest" else []
        widest = max((len(w) for text in whole for w in text.split()), default=0)
        if i < axes:
            widest = max(widest, min(whole_values, max(len(w) for row in table_rows for w in row[i].split())))
        table.add_column(h, overflow="fold", no_wrap=i >= axes and h not in ("busiest", "IQR"),
                         min_width=widest or None)
    for row in table_rows:
        table.add_row(*row)
    return table


def _fitting_table(head: list[str], table_rows: list[list[str]], axes: int) -> tuple[Table, bool]:
    """The first of these that fits the terminal: the varied values whole; a policy broken after its kind ("rl:"
    over "flaky_scheduler") and values up to WHOLE_VALUE wide whole; the values folded; and the busiest type over
    its share too. True with it when it is the first, every header whole too."""
    def broken(cell: str) -> str:
        return cell.replace(":", ":\n", 1) if ":" in cell and len(cell) > 12 else cell

    split = [[*map(broken, row[:axes]), *row[axes:]] for row in table_rows]
    stacked = [[*row[:-1], row[-1].replace(" ", "\n")] for row in split]
    for first, (cells, whole_values) in enumerate(((table_rows, 10**6), (split, WHOLE_VALUE), (split, 0),
                                                    (stacked, 0))):
        table = _variants_table(head, cells, axes, whole_values)
        printed = _printed(table)
        words = set(printed.split())
        if all(word in words for row in table_rows for word in row[-1].split()):
            # whole: each busiest type beside its share, each header unfolded ("bus" over "iest")
            return table, first == 0 and all(row[-1] in printed for row in table_rows) and all(
                h in words for h in head[axes:] if " " not in h)
    return table, False


def _printed(table: Table) -> str:
    """The table as printed at the terminal's width (rich cuts a table that its columns' least widths make wider
    than the terminal at the terminal's edge)."""
    with console.capture() as shown:
        console.print(table)
    return shown.get()


#: How wide a varied value may keep a column at 80 columns: a policy's name ("flaky_scheduler") whole, a longer
#: one (a plugin's module:Class) folded rather than the table cut at the terminal's edge.
WHOLE_VALUE = 15


@app.command()
@interruptible
def whatif(
    scenario: Annotated[Path, typer.Argument(help="the scenario as written, e.g. scenarios/flaky_lab.yaml")],
    vary: Annotated[Optional[list[str]], typer.Option(metavar="FIELD=V1,V2,...",
                                                      help="values of a field to try, e.g. devices.spectrometer.instances=1,2,3 "
                                                           "or devices.reactor.faults.fail_p=0,0.1; a whole section or list "
                                                           "too, '{fail_p: 0.1},{fail_p: 0.3, hang_p: 0.1}' (commas in "
                                                           "brackets do not split); repeatable: every combination "
                                                           "runs")] = None,
    schedulers: Annotated[Optional[str], typer.Option(help="comma-separated schedulers to vary too")] = None,
    planners: Annotated[Optional[str], typer.Option(help="comma-separated planners to vary too")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                      help="change a field of the scenario every variant "
                                                           "starts from, e.g. campaign.budget=200 "
                                                           "(repeatable)")] = None,
    seeds: Annotated[int, typer.Option(min=1, help="paired seeds per variant")] = 20,
    workers: Annotated[int, typer.Option(min=1, help="campaigns run in parallel")] = 2,
    budget_hours: Annotated[Optional[float], typer.Option(help="also name the cheapest variant (median cost) "
                                                               "that met every target in every run, its median "
                                                               "lab-hours to them within this many (a lab without "
                                                               "targets: its whole campaign's)")] = None,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write a row per variant to this CSV file")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print every variant and run as JSON instead of the table")] = False,
    save: Annotated[Optional[Path], typer.Option(help="draw the trade-offs into a Rerun recording, whatif.rrd, or a "
                                                     "picture, whatif.png")] = None,
) -> None:
    """The scenario as written and each variant, over the same seeds: lab-hours and cost to target, abandoned
    experiments and degraded samples (where any), the busiest device type, and the change against the scenario as
    written; for a lab of several campaigns, each campaign's lab-hours from its start to its end too."""
    writable("--csv", csv_out)
    recording_file("--save", save, or_picture=True)
    if budget_hours is not None and not 0 < budget_hours < math.inf:
        _fail(TwinError(f"--budget-hours {budget_hours:g}: give the lab-hours the targets must be met within, a "
                        "number above 0 (e.g. 5)"))
    from twin.tools.whatif import (AS_WRITTEN, axes_of, campaign_rows, caption, cheapest_within, costs_anything,
                                   has_targets as any_targets, header, in_seconds, measures, parse_vary, rows,
                                   runs_alike, summarise, variants, written_values)
    from twin.tools.whatif import whatif as run_whatif
    from twin.runtime import lab
    from twin.runtime.checks import checked, said_once

    split = lambda text: [x.strip() for x in text.split(",") if x.strip()] if text else None  # noqa: E731
    try:
        with said_once():  # a problem the variants share with the scenario as written: said once
            s = checked(lab.prepare(scenario, overrides=paired_assignments(set_ or [])), scenario,
                        planners=split(planners) or (), schedulers=split(schedulers) or (), virtual=True)
            varied = parse_vary(vary or [])
            chosen = variants(s, varied, split(schedulers), split(planners))
            axes = [name for name, _ in axes_of(varied, split(schedulers), split(planners))]
            for name in split(schedulers) or []:
                lab.make_scheduler(s, name)
            if len(chosen) == 1:
                raise TwinError("nothing to compare: give --vary FIELD=V1,V2 (or --schedulers / --planners) with a "
                                "value other than the scenario's")
            alike = runs_alike(s, chosen)
    except TwinError as exc:
        _fail(exc)
    if set_ and not as_json:
        console.print(f"as written: {scenario} with --set {', '.join(set_)}", highlight=False)
    if alike and seeds > 1:
        seeds = 1
        if not as_json:
            console.print(f"{s.name} runs alike on every seed (no chance in its durations or faults): one run per "
                          "variant", highlight=False)
    progress = bar_progress(as_json)
    cut = None
    with progress:
        bar = progress.add_task(f"{s.name}: {len(chosen)} variants × {counted(seeds, 'seed', 'seeds')}",
                                total=len(chosen) * seeds)
        try:
            results = run_whatif(s, chosen, seeds, workers, on_run=lambda o: progress.advance(bar))
        except KeyboardInterrupt as stop:  # the seeds every variant finished still make a table
            results, cut, csv_out, save = part_done(stop, as_json), stop, None, None  # a table, and no file of a part
    ran = len({o.seed for o in results})
    summary = summarise(results, chosen)
    best = cheapest_within(summary, budget_hours, any_targets(s)) if budget_hours is not None else None
    if csv_out is not None:
        _write_csv(csv_out, summary)
    if save is not None and save.suffix.lower() == ".png":
        from twin.view.whatif_picture import save_whatif_png

        chosen_within = (summary.index(best), budget_hours) if best else None
        save_whatif_png(save, s.name, summary, seeds, costs_anything(summary), in_seconds(summary), any_targets(s),
                        chosen_within)
    elif save is not None:
        from twin.view.recorder import save_whatif

        save_whatif(save, s.name, summary)
    if as_json:
        console.print_json(json.dumps({"scenario": s.name, "seeds": seeds, "variants": summary,
                                       "cheapest_within": best and best["variant"],
                                       "runs": [asdict(o) for o in results]}))
        return
    has_targets, shown = any_targets(s), measures(summary)
    seconds = in_seconds(summary)
    # the title above the table, not in it: a narrow table would fold it ("2 variants × 20" over "seeds")
    console.print(f"{s.name}: what if — {len(chosen)} variants × {ran if cut is None else f'{ran} of {seeds}'} "
                  f"{'seed' if seeds == 1 else 'seeds'}", highlight=False)
    table_rows = rows(summary, axes, written_values(s, axes), has_targets, shown)
    table, whole = _fitting_table(header(axes, shown, seconds), table_rows, len(axes))
    if not whole:  # the experiments' column gives its room to the values and the busiest type
        shown -= {"experiments"}
        table_rows = rows(summary, axes, written_values(s, axes), has_targets, shown)
        table, _ = _fitting_table(header(axes, shown, seconds), table_rows, len(axes))
    console.print(table)
    # wrapped at the terminal, not the table
    console.print(caption(has_targets, ran, shown, seconds, alike), highlight=False)
    say_ended_early([(o.variant, o.stopped) for o in results])
    if s.campaigns:
        names = list(summary[0]["per_campaign"])
        console.print("each campaign: median lab-h from its start to its end", highlight=False)
        per = Table(box=box.SIMPLE_HEAD, collapse_padding=True, pad_edge=False)
        for i, h in enumerate([*(header(axes)[:len(axes)]), *names]):
            per.add_column(h, overflow="fold", min_width=max(len(part) for part in h.split("\n")) if i < len(axes)
                           else None, justify="left" if i < len(axes) else "right")
        for row in campaign_rows(summary, axes, written_values(s, axes)):
            per.add_row(*row)
        console.print(per)
    base = next(r for r in summary if r["variant"] == AS_WRITTEN)
    out = max(base["stock_out"].items(), key=lambda kv: kv[1], default=("", 0.0))
    console.print(f"as written, the busiest device type is {base['bottleneck']} "
                  f"({100 * base['utilisation'].get(base['bottleneck'], 0):.0f} % busy)" +
                  (f", and {out[0]} was out of stock for {out[1]:.2f} lab-h (mean), until its refill" if out[1] > 0
                   else ""), highlight=False)
    if budget_hours is not None:
        costs = costs_anything(summary)
        found = best and (f"{best['variant']} (" + (f"cost {best['cost'][1]:,.0f}, " if costs else "") +
                          f"{best['lab_hours'][1]:.1f} lab-h)")
        judged = "every target met in every run" if any_targets(s) else "the whole campaign: the lab has no targets"
        console.print(f"{'cheapest' if costs else 'fastest (nothing costs anything)'} within {budget_hours:g} lab-h "
                      f"(median; {judged}): {found or 'none of these variants'}", highlight=False)
    for path in (csv_out, save):
        if path is not None:
            console.print(f"wrote {path}", highlight=False)
    if cut is not None:
        stopped_partway(cut, f"the {counted(ran, 'seed', 'seeds')} every variant finished")


def _write_csv(path: Path, summary: list[dict]) -> None:
    types = sorted({t for row in summary for t in row["utilisation"]})
    names = list(dict.fromkeys(n for row in summary for n in row["per_campaign"]))
    stocks = list(dict.fromkeys(n for row in summary for n in row["stock_out"]))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["variant", "runs", "reached", "lab_h_q1", "lab_h_median", "lab_h_q3", "lab_h_change_median",
                    "cost_median", "cost_change_median", "experiments_median", "abandoned_mean", "degraded_mean",
                    *[f"utilisation_{t}" for t in types], "busiest", *[f"campaign_h_{n}" for n in names],
                    *[f"out_of_stock_h_{n}" for n in stocks]])
        for row in summary:
            change, cost_change = row["lab_hours_change"], row["cost_change"]
            w.writerow([inert(row["variant"]), row["runs"], row["reached"], *[round(x, 4) for x in row["lab_hours"]],
                        round(change[1], 4) if change else "", round(row["cost"][1], 2),
                        round(cost_change[1], 2) if cost_change else "", row["experiments"],
                        round(row["abandoned"], 3), round(row["degraded"], 3),
                        *[round(row["utilisation"].get(t, 0.0), 4) for t in types], row["bottleneck"],
                        *[round(row["per_campaign"][n], 4) if n in row["per_campaign"] else "" for n in names],
                        *[round(row["stock_out"].get(n, 0.0), 4) for n in stocks]])
