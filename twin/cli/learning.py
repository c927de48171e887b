"""`twin train` and `twin bench`: training agents in the twin and comparing them over seeds."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer
from rich.table import Table

from twin.core import plugins
from twin.cli.common import (_fail, app, assignments, bar_progress, bench_app, console, err, interruptible,
                             exit_status, fitted_width, machine_output, narrow_table, paired_assignments, print_table,
                             recording_file, refuse_disagreeing, say_ended_early, sigterm_unwinds, stopped_by,
                             stopped_partway, part_done, writable)
from twin.core.errors import TwinError
from twin.core.whole_files import kept_from_others

if TYPE_CHECKING:  # the commands import the runtime when they run: twin ctl or router need none of it
    from twin.scenario import Scenario

#: What `twin bench planners` compares unless told.
DEFAULT_PLANNERS = "random,lhs,gp-bo~seq,gp-bo"


@app.command()
def train(
    scenario: Annotated[Path, typer.Argument(help="the scenario to train in, e.g. scenarios/quantum_dots.yaml")],
    out: Annotated[Path, typer.Option(help="where to save the policy (.zip, with a .json beside it)")],
    agent: Annotated[str, typer.Option(help="scheduler (the rl scheduler), planner (the rl planner), "
                                            "controller or controller-residual (the reactor's heater), route "
                                            "(the route search's expansion prior)")] = "scheduler",
    steps: Annotated[int, typer.Option(min=1, help="environment steps")] = 200_000,
    seed: Annotated[int, typer.Option(help="training seed")] = 0,
    envs: Annotated[int, typer.Option(min=1, help="environments stepped together (imitation: labs rolled out "
                                                  "together, in up to one worker process per core)")] = 4,
    eval_every: Annotated[int, typer.Option(min=1, help="evaluate (and keep the best policy) every this many steps")] = 20_000,
    save: Annotated[Optional[Path], typer.Option(help="also record the evaluation curve to Rerun, e.g. curve.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="show the evaluation curve live in the Rerun viewer")] = False,
    init: Annotated[Optional[Path], typer.Option(help="start from this policy (the scheduler, needed by "
                                                     "training.teacher: self; without it a lab that names no teacher "
                                                     "starts from the shipped general one where it fits; or a route "
                                                     "prior, P.pt)")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", metavar="FIELD=VALUE",
                                                      help="override a scenario field, e.g. "
                                                           "training.teacher=self; repeatable")] = None,
) -> None:
    """Train an agent in the twin; the evaluation curve is printed as it goes (and recorded to Rerun if asked)."""
    from twin.runtime import lab
    from twin.runtime.checks import checked
    from twin.runtime.fast_device import FastRuntimeRefused

    if out.is_dir():  # its name would get the suffix: --out runs saved runs.zip beside the directory
        _fail(TwinError(f"--out {out} is a directory: give the policy's file, e.g. {out / 'policy.zip'}"))
    writable("--out", out.with_suffix(".zip"), out.with_suffix(".json"))
    recording_file("--save", save)
    try:
        # a scheduler's training makes a new policy: the scenario's own scheduler (say a policy that does not fit
        # this lab, which the misfit message tells the user to train) is not loaded
        s = checked(lab.prepare(scenario, overrides=assignments(set_ or [])), scenario, benched=agent == "scheduler",
                    virtual=True)
        trainer = plugins.load("trainers", agent)
        if init is not None and agent not in ("scheduler", "route"):
            raise TwinError(f"--init starts the scheduler's or the route prior's training from a policy; the {agent} "
                            f"trainer has no such option (leave --init out)")
        if init is not None and not init.exists():
            raise TwinError(f"--init {init}: no such policy file")
    except TwinError as exc:
        _fail(exc)
    kept = out.with_suffix(".zip")
    before = kept.stat().st_mtime_ns if kept.exists() else None
    writing = contextlib.ExitStack()  # --out kept from another training until this one ends
    try:
        writing.enter_context(kept_from_others(kept, f"--out {kept}: another training is writing it now: wait for "
                                                     "it to end, or give --out another file (nothing has run yet)"))
    except TwinError as exc:
        _fail(exc)
    recording = None
    if save or viewer:
        from twin.view.recorder import log_curve, open_recording

        try:
            recording = open_recording(f"train-{agent}-{s.name}", save=save, viewer=viewer, campaign_layout=False)
        except TwinError as exc:  # its file another run is recording
            writing.close()
            _fail(exc)
        for message in recording.messages:
            err.print(message, highlight=False)
    progress = bar_progress()

    trained = [0]
    bars: list = []  # the bar starts at the trainer's first word: a lab it refuses gets the reason and no bar

    def report(done: int, result: dict | None) -> None:
        trained[0] = max(trained[0], done)
        if not bars:
            bars.append(progress.add_task(f"training the {agent} on {s.name}", total=steps))
        bar = bars[0]
        if not (result and result.keys() == {"policy"}):  # a remark (a fall-back, a policy kept) leaves the bar
            progress.update(bar, completed=done, total=max(steps, done))  # rounds of labels can end past it
        if result:
            fields = "  ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                               for k, v in result.items() if k != "policy")
            if recording is not None:
                numbers = {k: v for k, v in result.items() if isinstance(v, (int, float))}
                log_curve(recording, done, numbers, f"training/{result['policy'].split(':')[0].replace(' ', '_')}")
            progress.console.print(f"{done:>9,} steps  {result['policy']:14} {fields}", highlight=False)

    with writing, progress, sigterm_unwinds():
        try:
            path = trainer(s, steps, out, seed=seed, envs=envs, eval_every=eval_every, on_progress=report,
                           **({"init": init} if init is not None else {}))
        except FastRuntimeRefused as exc:
            _fail(TwinError(f"{exc.why}. `twin train` runs every episode on the fast runtime (virtual time, "
                            "in-process)" + (f": give devices.{exc.device_type}.twin: {{driver: NAME}}, a simulated "
                                             "driver of its steps, and training runs that instead (docs/drivers.md)"
                                             if exc.device_type else "")))
        except (TwinError, ValueError) as exc:
            _fail(TwinError(str(exc)))
        except KeyboardInterrupt as stop:
            progress.stop()
            saved = kept.exists() and kept.stat().st_mtime_ns != before
            err.print(f"{stopped_by(stop)}; " + (f"the best policy so far is {kept}" if saved else
                                                 "no policy saved yet" + (f" ({kept} is an earlier training's)"
                                                                          if kept.exists() else "")),
                      highlight=False)
            raise typer.Exit(exit_status(stop)) from None
        finally:
            if recording is not None:
                recording.close()
    console.print(f"saved {path} (and {path.with_suffix('.json').name})")
    verdict = kept_round(path, s, scenario)
    if verdict:
        err.print(verdict, highlight=False)
    if trained[0] > steps:
        err.print(f"trained {trained[0]:,} steps for --steps {steps:,}: training goes in rounds (of whole episodes, "
                  "or of PPO's rollouts on every environment), and a round begun is finished", highlight=False)


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


def kept_round(path: Path, s: Scenario, scenario: Path) -> str:
    """Which evaluation round a scheduler's training kept, what its score says, and how to compare it with the
    rule on more runs ("" for a policy whose file keeps no rule-relative curve: a planner, a controller)."""
    from twin.learning.policies import read_meta

    meta = read_meta(path)
    scored = [c for c in meta.get("curve", []) if isinstance(c.get("score"), (int, float))]
    rule = meta.get("best_rule")
    if not scored or not rule:
        return ""
    best = min(scored, key=lambda c: c["score"])
    verdict = ("it did better than the rule" if best["score"] < 0.995 else "level with the rule"
               if best["score"] <= 1.005 else "the rule did better (train longer, or keep the rule)")
    if s.campaigns:
        compare = f"in each campaign of the lab: twin whatif {scenario} --schedulers {rule},rl:{path}"
    elif s.jobshop is not None:
        compare = f"on shops it never trained on: twin bench schedulers {scenario} --jobshop DIR --schedulers " \
                  f"{rule},rl:{path}"
    else:
        compare = (f"on the lab's variants, 40 paired seeds: twin bench schedulers {scenario} --shapes --seeds 40 "
                   f"--schedulers {rule},rl:{path}")
    said = (f"kept the round at {best['steps']:,} steps: score {best['score']:.3f}, its objective ÷ the best rule's "
            f"({rule}) on the evaluation runs (below 1 is better): {verdict}. Compare them {compare}")
    solver = best.get("vs cp-sat")
    if isinstance(solver, (int, float)) and solver > 1.03 and not s.campaigns and s.jobshop is None:
        # a learnt policy imitates a rule there (cp-sat teaches job shops only): the better schedules exist
        said += (f". CP-SAT, scheduling the lab online, did {100 * (1 - 1 / solver):.0f} % better than it on the "
                 f"evaluation run (vs cp-sat {solver:.2f}): compare it too (--schedulers {rule},cp-sat,rl:{path}), or run the "
                 "lab with campaign.scheduler: cp-sat (up to campaign.scheduler_options.time_limit_s of wall time "
                 "a decision)")
    return said


def one_campaign(s: Scenario, path: Path, what: str) -> Scenario:
    """``s``, unless it is a lab of several campaigns: a bench runs one campaign's lab (it failed on the lab's own
    sections, "chemistry.parameters: empty", which the campaigns fill), and `twin whatif` compares the lab."""
    if not s.campaigns:
        return s
    names = ", ".join(c.name for c in s.campaigns)
    raise TwinError(f"{path}: a lab of {len(s.campaigns)} campaigns ({names}), and `twin bench {what}` compares "
                    f"{what} on one campaign; `twin whatif {path} --{what} A,B` runs the lab with each (in every "
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
        stopped_partway(cut, f"the {ran} seed(s) every planner finished")


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
    from twin.tools.scheduler_bench import (BOUND_S, COUNTS, HEADER, bench, bound, caption, deterministic,
                                            load_variant, played_ahead, rows, shops, slow_schedulers)

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
            best = bound(s, on_long=None if as_json else lambda: err.print(
                f"{title}: CP-SAT solving the shop for the bound (up to {BOUND_S:.0f} s) ...", highlight=False))
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
                                 f"{title} — {runs}{'' if cut is None else f' of {seeds}'} run(s) per scheduler" +
                                 (f"; {best.title()}" if best else ""),
                                 caption("lab-s" if s.jobshop else "lab-h", bound=best, silent=silent, ahead=ahead))
            for row in table_rows:
                table.add_row(*(row[i] for i in shown))
            print_table(table)
            say_ended_early([(r.scheduler, r.stopped) for v in results.values() for r in v])
            if cut is not None:
                stopped_partway(cut, f"the {runs} seed(s) of {title} every scheduler finished")
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
        stopped_partway(cut, f"the {len(results)} shape(s) of {total} finished")
