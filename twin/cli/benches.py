"""`twin bench planners` and `twin bench schedulers`: comparing planners and schedulers over paired seeds."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.table import Table

from twin.core.printable import shell_word
from twin.cli.common import (bar_progress, bench_app, err, _fail, fitted_width, machine_output, narrow_table,
                             paired_assignments, print_table, refuse_disagreeing, say_ended_early, writable)
from twin.cli.stopping import interruptible, part_done, stopped_partway
from twin.core.counts import counted
from twin.core.errors import TwinError

if TYPE_CHECKING:  # the commands import the runtime when they run: twin ctl or router need none of it
    from twin.scenario import Scenario


#: What `twin bench planners` compares unless told.
DEFAULT_PLANNERS = "random,lhs,gp-bo~seq,gp-bo"


def _benched(s: Scenario, names: list[str]) -> dict[str, object]:
    """The schedulers a bench runs, each made once to check it; an option of ``campaign.scheduler_options`` that
    none of them (nor any installed scheduler) takes is refused as misspelt."""
    from twin.runtime import lab
    from twin.runtime.assembly import untaken_option

    made = {name: lab.make_scheduler(s, name) for name in names}
    problem = untaken_option(s, "schedulers", names)
    if problem:
        raise TwinError(problem)
    return made


def say_slow(slow: str) -> None:
    """What a bench may wait for (``scheduler_bench.slow_schedulers``), said before its runs."""
    if slow:
        err.print(f"{slow} (workers share them out; Ctrl-C stops the bench)", highlight=False)


def _said_of(title: str, text: str) -> None:
    err.print(f"{title}: {text}", highlight=False)


def _compared_table(header: list[str], title: str, caption: str, rows: list[list[str]], first_compared: int) -> Table:
    """The shapes table with each comparison ("+0.30 ± 0.55\nsame") on one line, else over two, else the
    difference, its interval and the verdict each on a line of its own: the first that fits the terminal with no
    line of a comparison broken (where rich would fold "+0.30 ± 0.55 same" into "+0.30 ±" over "0.55 same")."""
    def laid_out(layout: Callable[[str], str], whole_words: bool) -> Table:
        table = narrow_table(header, title, caption)
        for row in rows:
            table.add_row(*row[:first_compared], *map(layout, row[first_compared:]))
        for i, column in enumerate(table.columns):  # print_table keeps a column at least this wide
            if i >= first_compared or whole_words:  # a comparison's lines whole; a shape's words too, to fit
                parts = [p for cell in column._cells for p in str(cell).split("\n" if i >= first_compared else None)]
                column.min_width = max(len(part) for part in parts)
        return table

    for layout in (lambda cell: cell.replace("\n", " "), lambda cell: cell):
        table = laid_out(layout, whole_words=True)
        if fitted_width(table) is not None:
            return table
    return laid_out(lambda cell: cell.replace(" ± ", "\n± "), whole_words=False)


def one_campaign(s: Scenario, path: Path, what: str) -> Scenario:
    """``s``, unless it is a lab of several campaigns: a bench runs one campaign's lab (it failed on the lab's own
    sections, "chemistry.parameters: empty", which the campaigns fill), and `twin whatif` compares the lab."""
    if not s.campaigns:
        return s
    names = ", ".join(c.name for c in s.campaigns)
    raise TwinError(f"{path}: a lab of {len(s.campaigns)} campaigns ({names}), and `twin bench {what}` compares "
                    f"{what} on one campaign; `twin whatif {shell_word(path)} --{what} A,B` runs the lab with each "
                    "(in every "
                    f"campaign) and gives each campaign's lab-hours, or bench one campaign's own scenario (its "
                    f"chemistry, workflow and campaign with the lab's devices)")


@bench_app.command("planners")
@interruptible
def bench_planners(
    scenario: Annotated[Path, typer.Argument(help="a scenario with targets, e.g. scenarios/quantum_dots.yaml")],
    seeds: Annotated[int, typer.Option(min=1, help="seeds per planner")] = 20,
    planners: Annotated[str, typer.Option(help="comma-separated; name~seq runs one experiment at a time, "
                                                "name@SCHEDULER with another scheduler (gp-bo@fifo~seq)")]
    = DEFAULT_PLANNERS,
    workers: Annotated[int, typer.Option(min=1, help="campaigns run in parallel")] = 2,
    budget: Annotated[Optional[int], typer.Option(min=1, help="override the scenario's budget (a larger one censors "
                                                              "less)")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                      help="override a scenario field, e.g. "
                                                           "campaign.max_in_flight=2; repeatable")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print the rows and every run as JSON instead")] = False,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write every run to this CSV file")] = None,
) -> None:
    """Experiments and lab-hours to target (median [IQR]) for each planner over many seeds, vs random."""
    writable("--csv", csv_out)
    from dataclasses import asdict

    from twin.runtime import lab
    from twin.runtime.checks import checked
    from twin.tools.planner_bench import HEADER, bench, caption, parse, rows

    names = [p.strip() for p in planners.split(",") if p.strip()]
    if not names:
        _fail(TwinError(f"--planners {planners!r}: name at least one planner, e.g. --planners random,gp-bo"))
    sets = paired_assignments(set_ or [], ("campaign.planner", "--planners"))
    refuse_disagreeing(sets, {"campaign.budget": ("--budget", budget)})
    overrides = {**sets, **({"campaign.budget": budget} if budget else {})}
    try:
        parsed = [parse(name) for name in names]
        s = one_campaign(checked(lab.prepare(scenario, overrides=overrides), scenario,
                                 planners=[planner for planner, _, _ in parsed],
                                 schedulers=[scheduler for _, scheduler, _ in parsed if scheduler], virtual=True),
                         scenario,
                         "planners")
        for name in names:
            planner, scheduler, _ = parse(name)
            lab.make_planner(s.model_copy(update={"campaign": s.campaign.model_copy(update={"planner": planner})}))
            if scheduler:
                lab.make_scheduler(s, scheduler)
    except TwinError as exc:
        _fail(exc)
    progress = bar_progress(as_json)
    cut = None
    with progress:
        bar = progress.add_task(f"{s.name}: {len(names)} planners × {seeds} seeds", total=len(names) * seeds)
        try:
            results = bench(s, names, seeds, workers, on_trial=lambda t: progress.advance(bar))
        except KeyboardInterrupt as stop:  # the seeds every planner finished still make a table
            results, cut, csv_out = part_done(stop, as_json), stop, None  # a table, and no file of a part
    ran = len(next(iter(results.values())))
    table_rows = rows(results)
    runs = [asdict(t) for trials in results.values() for t in trials]
    if machine_output(as_json, csv_out, HEADER, table_rows, runs, scenario=s.name, seeds=seeds):
        return
    # a lab where nothing costs has a cost column of noughts: its room goes to the planners' names
    costs = any(t.cost > 0 for trials in results.values() for t in trials)
    shown = [i for i, h in enumerate(HEADER) if costs or h != "cost"]
    table = narrow_table([HEADER[i] for i in shown], f"{s.name} — {ran if cut is None else f'{ran} of {seeds}'} "
                         f"seeds, budget {s.campaign.budget}, {s.campaign.max_in_flight} in the lab", caption(costs))
    for row in table_rows:
        table.add_row(*(row[i] for i in shown))
    print_table(table)
    say_ended_early([(t.planner, t.stopped) for trials in results.values() for t in trials])
    if cut is not None:
        stopped_partway(cut, f"the {counted(ran, 'seed', 'seeds')} every planner finished")


BENCHED = ("campaign.scheduler", "--schedulers")  # what a scheduler bench runs each of


@bench_app.command("schedulers")
@interruptible
def bench_schedulers(
    scenario: Annotated[Path, typer.Argument(help="a scenario, e.g. scenarios/flaky_lab.yaml or scenarios/jobshop.yaml")],
    seeds: Annotated[int, typer.Option(min=1, help="seeds per scheduler (a deterministic job shop runs once)")] = 20,
    schedulers: Annotated[str, typer.Option(help="comma-separated: rules, cp-sat, rl:POLICY.zip")] = "fifo,spt,mwkr,least-loaded,oldest-sample",
    jobshop: Annotated[Optional[str], typer.Option(help="job-shop files to run instead of the scenario's, comma-separated "
                                                       "(e.g. jobshop/la01.txt,jobshop/ft10.txt), beside the scenario "
                                                       "or in the current directory; a collection (OR-Library's "
                                                       "jobshop1.txt, Taillard's tai15_15.txt) runs each of its "
                                                       "instances, a directory each of its files")] = None,
    workers: Annotated[int, typer.Option(min=1, help="campaigns run in parallel")] = 2,
    budget: Annotated[Optional[int], typer.Option(min=1, help="override the scenario's budget")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                      help="override a scenario field, e.g. "
                                                           "devices.reactor.instances=1 (another lab shape); repeatable")] = None,
    shapes: Annotated[bool, typer.Option("--shapes", help="run a family of variants of the lab (instances ×2, "
                                                          "a bottleneck, a flaky stage, fast-degrading samples) "
                                                          "and compare each scheduler with the best rule, "
                                                          "paired seeds, 95 % CI")] = False,
    random_labs: Annotated[int, typer.Option(help="with --shapes: also N whole other labs drawn at random "
                                                  "(2–5 device types; training.random_labs)")] = 0,
    by: Annotated[str, typer.Option(help="with --shapes: compare on makespan, or on the objective "
                                         "(training.weights: makespan, degraded samples, abandoned experiments)")]
    = "makespan",
    as_json: Annotated[bool, typer.Option("--json", help="print the rows and every run as JSON instead")] = False,
    csv_out: Annotated[Optional[Path], typer.Option("--csv", help="write every run to this CSV file")] = None,
) -> None:
    """Makespan, gap to the CP-SAT bound, utilisation, degraded and lost samples, decision latency per scheduler."""
    shapes_only = [f"--{name} {value}" for name, value, default in (("random-labs", random_labs, 0),
                                                                    ("by", by, "makespan")) if value != default]
    if shapes_only and not shapes:
        _fail(TwinError(f"{' and '.join(shapes_only)}: {'options' if len(shapes_only) > 1 else 'an option'} of "
                        "--shapes, which this bench is not: add --shapes"))
    writable("--csv", csv_out)
    from dataclasses import asdict

    from twin.runtime import lab
    from twin.runtime.checks import checked
    from twin.tools.planner_bench import bench_pool
    from twin.tools.scheduler_bench import (COUNTS, HEADER, bench, bound_in, caption, deterministic, load_variant,
                                            played_ahead, rows, shops, slow_schedulers)

    names = [p.strip() for p in schedulers.split(",") if p.strip()]
    if not names:
        _fail(TwinError(f"--schedulers {schedulers!r}: name at least one scheduler, e.g. --schedulers fifo,mwkr"))
    sets = paired_assignments(set_ or [], BENCHED)
    refuse_disagreeing(sets, {"campaign.budget": ("--budget", budget)})
    if shapes:
        _bench_shapes(scenario, names, seeds, workers, budget, sets, random_labs, as_json, csv_out, by)
        return
    tables: list[dict] = []
    all_runs: list[dict] = []
    try:  # a collection of shops (OR-Library's jobshop1.txt) is each of its instances
        if jobshop and lab.prepare(scenario).jobshop is None:
            raise TwinError(f"--jobshop runs job shops in a job-shop scenario's lab, and {scenario} has no `jobshop:` "
                            "section: give one, e.g. scenarios/jobshop.yaml")
        files: list = shops(scenario, [f.strip() for f in jobshop.split(",")]) if jobshop else [(None, None)]
    except TwinError as exc:
        _fail(exc)
    with bench_pool(workers) as pool:  # one set of workers for every shop
        for file, instance in files:
            try:
                s = one_campaign(checked(load_variant(scenario, file, budget, sets, instance), scenario, benched=True,
                                         virtual=True),
                                 scenario, "schedulers")
                made = _benched(s, names)
            except TwinError as exc:
                _fail(exc)
            if not as_json:
                say_slow(slow_schedulers(s, made, 1 if deterministic(s) else seeds))
            title = instance or f"{Path(file).stem if file else s.name}"
            best = bound_in(pool, s, say=None if as_json else functools.partial(_said_of, title))
            optimum = best.lab_s if best else None
            progress = bar_progress(as_json)
            cut = None
            with progress:
                bar = progress.add_task(f"{title}: {len(names)} schedulers",
                                        total=len(names) * (1 if deterministic(s) else seeds))
                try:
                    results = bench(s, names, seeds, workers, on_run=lambda r: progress.advance(bar), pool=pool)
                except KeyboardInterrupt as stop:  # the seeds every scheduler finished still make a table
                    results, cut, csv_out = part_done(stop, as_json), stop, None  # a table, and no file of a part
            runs = len(next(iter(results.values())))
            table_rows = rows(results, optimum, 1.0 if s.jobshop else 3600.0)
            all_runs += [{"lab": title, **asdict(r)} for v in results.values() for r in v]
            ahead = played_ahead(s, names)
            tables.append({"lab": title, "bound_s": optimum, "bound_proven": best.proven if best else None,
                           "played_ahead": ahead, "rows": [dict(zip(HEADER, r)) for r in table_rows]})
            if as_json:
                continue
            # no bound: no column; counts that are nought for every scheduler (a job shop's) leave the room to names
            silent = {h for i, h in enumerate(HEADER) if h in COUNTS and all(float(r[i]) == 0 for r in table_rows)}
            shown = [i for i, h in enumerate(HEADER) if (optimum or h != "vs bound") and h not in silent]
            table = narrow_table([HEADER[i] for i in shown],
                                 f"{title} — {runs}{'' if cut is None else f' of {seeds}'} "
                                 f"{'run' if (runs if cut is None else seeds) == 1 else 'runs'} per scheduler" +
                                 (f"; {best.title()}" if best else ""),
                                 caption("lab-s" if s.jobshop else "lab-h", bound=best if optimum else None,
                                         silent=silent, ahead=ahead))  # a 0-s optimum: no gap, no column
            for row in table_rows:
                table.add_row(*(row[i] for i in shown))
            print_table(table)
            say_ended_early([(r.scheduler, r.stopped) for v in results.values() for r in v])
            if cut is not None:
                stopped_partway(cut, f"the {counted(runs, 'seed', 'seeds')} of {title} every scheduler finished")
    machine_output(as_json, csv_out, HEADER, [], all_runs, labs=tables)


def _bench_shapes(scenario: Path, names: list[str], seeds: int, workers: int, budget: int | None,
                  changes: dict, random_labs: int = 0, as_json: bool = False, csv_out: Path | None = None,
                  by: str = "makespan") -> None:
    from dataclasses import asdict

    from twin.runtime.checks import checked
    from twin.tools.planner_bench import label
    from twin.tools.scheduler_bench import load_variant, slow_schedulers
    from twin.tools.shape_bench import measure, shapes, variants, verdict

    try:
        s = one_campaign(checked(load_variant(scenario, None, budget, changes), scenario, benched=True,
                                         virtual=True), scenario,
                         "schedulers")
        measure(s, by)  # said before the progress bar
        made = _benched(s, names)
    except TwinError as exc:
        _fail(exc)
    if s.jobshop is not None:
        _fail(TwinError("--shapes varies a lab's devices and samples; for job shops use --jobshop FILES"))
    if not as_json:
        say_slow(slow_schedulers(s, made, seeds * len(variants(s, random_labs))))
    others = list(names)
    header = ["shape", "best rule", "its mean h", *[label(n) for n in others]]
    what = "makespan lab-h" if by == "makespan" else (
        f"objective in lab-h (makespan, and {s.training.weights.degraded:g} typical steps per degraded sample, "
        f"{s.training.weights.abandoned:g} per abandoned experiment, ÷ {s.training.weights.time:g}: "
        "training.weights)")
    # a policy's or a class's name breaks after its prefix ("rl:" over "flaky_scheduler"), not at the column's edge
    shown = [*header[:3], *(h.replace(":", ":\n", 1) for h in header[3:])]
    chance = ("campaigns end when every target is met (campaign.stop_on_target), and which experiment meets them "
              "first depends on the order they ran, so chance weighs on every row; --set "
              "campaign.stop_on_target=false compares the schedulers on the whole budget"
              if s.chemistry.targets and s.campaign.stop_on_target else "")
    title = f"{s.name}: each scheduler minus the shape's best rule, {what} (mean of {seeds} paired seeds ± 95 % CI)"
    progress = bar_progress(as_json)
    cut, total = None, len(variants(s, random_labs))
    with progress:
        bar = progress.add_task(f"{s.name}: shapes", total=total)
        try:
            results = shapes(s, names, seeds, workers, on_shape=lambda c: progress.advance(bar),
                             random_labs=random_labs, by=by)
        except KeyboardInterrupt as stop:  # the shapes finished still make a table
            results, cut, csv_out = part_done(stop, as_json), stop, None  # a table, and no file of a part
    table_rows, comparisons, runs = [], [], []
    for c in results:
        cells = []
        for n in others:
            diff, half = c.diffs[n]
            said = f"{diff / 3600:+.2f} ± {half / 3600:.2f}\n{verdict(diff, half)}"  # laid out by _compared_table
            cells.append("—" if n == c.best_rule else said)
            comparisons.append({"shape": c.shape, "scheduler": n, "by": by, "best_rule": c.best_rule,
                                "best_rule_mean_h": c.best_mean_s / 3600, "diff_h": diff / 3600,
                                "ci95_h": half / 3600, "verdict": verdict(diff, half)})
            runs += [{"shape": c.shape, **asdict(r), "makespan_h": r.makespan_s / 3600} for r in c.runs[n]]
        table_rows.append([c.shape, label(c.best_rule), f"{c.best_mean_s / 3600:.2f}", *cells])
    if machine_output(as_json, csv_out, header, [[cell.replace("\n", " ") for cell in row] for row in table_rows],
                      runs, scenario=s.name, seeds=seeds, comparisons=comparisons):
        return
    if cut is not None:
        title += f"; {len(results)} of {total} shapes"
    print_table(_compared_table(shown, title, chance, table_rows, first_compared=3))
    say_ended_early([(n, r.stopped) for c in results for n in others for r in c.runs[n]])
    if cut is not None:
        stopped_partway(cut, f"the {counted(len(results), 'shape', 'shapes')} of {total} finished")
