"""``twin``: a thin command line over the Python API in ``twin.lab``."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from twin import lab, plugins
from twin.errors import TwinError
from twin.journal import read_run
from twin.planner_bench import DEFAULT_PLANNERS
from twin.report import render_summary
from twin.scenario import json_schema, load
from twin.summary import Summary
from twin.watch import RecordOptions, open_observer
from twin.watch import replay as replay_journal
from twin.watch import watch as watch_lab

app = typer.Typer(help="labtwin: a digital twin of a self-driving lab.", no_args_is_help=True,
                  pretty_exceptions_enable=False, add_completion=False)
device_app = typer.Typer(help="Run one device actor in this process.", no_args_is_help=True)
app.add_typer(device_app, name="device")
bench_app = typer.Typer(help="Compare planners and schedulers over many seeds.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
scheduler_app = typer.Typer(help="Run a scheduler agent in this process.", no_args_is_help=True)
driver_app = typer.Typer(help="Write your own device drivers.", no_args_is_help=True)
app.add_typer(driver_app, name="driver")
app.add_typer(scheduler_app, name="scheduler")
console = Console()
err = Console(stderr=True, soft_wrap=True)


def _fail(exc: TwinError) -> None:
    err.print(f"[bold red]error:[/] {exc}", highlight=False)
    raise typer.Exit(2)


@app.command()
def run(
    scenario: Annotated[Path, typer.Argument(help="a scenario file, e.g. scenarios/quantum_dots.yaml")],
    seed: Annotated[Optional[int], typer.Option(help="override campaign.seed")] = None,
    clock: Annotated[Optional[str], typer.Option(help="virtual | scaled | wall")] = None,
    speed: Annotated[Optional[float], typer.Option(help="lab seconds per wall second (scaled clock)")] = None,
    bus: Annotated[Optional[str], typer.Option(help="zenoh | memory")] = None,
    budget: Annotated[Optional[int], typer.Option(help="override campaign.budget")] = None,
    planner: Annotated[Optional[str], typer.Option(help="override campaign.planner (twin bench planners lists them)")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="override campaign.scheduler")] = None,
    journal: Annotated[Optional[Path], typer.Option(help="where to write the SQLite journal")] = None,
    external: Annotated[Optional[list[str]], typer.Option(help="a device served by another process")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447")] = None,
    save: Annotated[Optional[Path], typer.Option(help="save a Rerun recording, e.g. run.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="open the Rerun viewer and stream live")] = False,
    serve: Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1 (URL printed)")] = False,
    serve_port: Annotated[int, typer.Option(help="gRPC port for --serve (0: any free one)")] = 0,
    web_port: Annotated[int, typer.Option(help="web viewer port for --serve (0: any free one)")] = 0,
    quiet: Annotated[bool, typer.Option(help="no progress bar")] = False,
    json_out: Annotated[bool, typer.Option("--json", help="print the summary as JSON")] = False,
) -> None:
    """Run a campaign and print its summary."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    overrides: dict = {f"campaign.{k}": v for k, v in (("budget", budget), ("planner", planner),
                                                        ("scheduler", scheduler)) if v is not None}
    if listen:
        overrides["bus.listen"] = list(listen)
    record = RecordOptions(save, viewer, serve, serve_port, web_port)
    recording = None
    try:
        s = lab.prepare(scenario, seed=seed, clock=clock, speed=speed, bus=bus, overrides=overrides)
        observer = None
        if record.wanted:
            observer, recording = open_observer(record, lab.recording_id(s))
            for message in recording.messages:
                err.print(message, highlight=False)
        progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("lab {task.fields[lab_h]:.1f} h"), TimeElapsedColumn(),
                            console=err, disable=quiet or json_out, transient=False)
        with progress:
            bar = progress.add_task(f"{s.name} ({s.clock.mode} clock, {s.bus.kind} bus)",
                                    total=s.campaign.budget, lab_h=0.0)

            def on_progress(orch) -> None:
                finished = sum(1 for e in orch.experiments if e.status in ("done", "abandoned"))
                progress.update(bar, completed=finished, lab_h=orch.elapsed_s / 3600)

            summary = lab.run(s, journal=journal, external_devices=set(external or ()), on_progress=on_progress,
                              observer=observer)
    except TwinError as exc:
        if recording is not None:
            recording.stop_serving()
        _fail(exc)
    if json_out:
        print(json.dumps(summary.to_dict(), indent=2))
    else:
        render_summary(summary, console)
    if recording is not None:
        recording.close()
        if save:
            err.print(f"recording saved: {save}  (open it with: rerun {save})", highlight=False)
        _keep_serving(recording)


def _keep_serving(recording) -> None:
    """--serve: the recording stays up until Ctrl-C, so it can be looked at after the run."""
    if recording.server is None:
        return
    err.print(f"the finished campaign is served at {recording.url} — Ctrl-C to stop", highlight=False)
    try:
        recording.server.wait()
    except KeyboardInterrupt:
        pass
    finally:
        recording.stop_serving()


@app.command()
def watch(
    lab_name: Annotated[str, typer.Option("--lab", help="the lab to watch (the scenario's `lab` field)")],
    connect: Annotated[Optional[list[str]], typer.Option(help="Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447")] = None,
    listen: Annotated[Optional[list[str]], typer.Option(help="listen instead, for a lab that connects to us")] = None,
    save: Annotated[Optional[Path], typer.Option(help="save the recording, e.g. watch.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="open the Rerun viewer")] = False,
    serve: Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1")] = False,
    follow: Annotated[bool, typer.Option(help="keep watching after the campaign ends")] = False,
) -> None:
    """Attach to a lab running in another process and record what it does."""
    if not (connect or listen):
        _fail(TwinError("give --connect ENDPOINT (where the lab listens: twin run --listen ...) or --listen ENDPOINT"))
    record = RecordOptions(save, viewer, serve)
    if not record.wanted:
        _fail(TwinError("nothing to do: give --save FILE, --viewer or --serve"))
    try:
        observer = watch_lab(lab_name, record, list(connect or []), list(listen or []), follow)
    except TwinError as exc:
        _fail(exc)
    err.print(f"recorded {observer.spectra} spectra, {observer.finished} finished experiments"
              + (f" to {save}" if save else ""), highlight=False)


@app.command()
def replay(
    journal: Annotated[Path, typer.Argument(help="a run's journal, runs/<run>.db")],
    save: Annotated[Optional[Path], typer.Option(help="save the rebuilt recording, e.g. replay.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="open the Rerun viewer")] = False,
    serve: Annotated[bool, typer.Option(help="serve a web viewer on 127.0.0.1")] = False,
) -> None:
    """Rebuild a run's Rerun recording from its journal alone."""
    record = RecordOptions(save, viewer, serve)
    if not record.wanted:
        _fail(TwinError("nothing to do: give --save FILE, --viewer or --serve"))
    try:
        observer = replay_journal(journal, record)
    except TwinError as exc:
        _fail(exc)
    err.print(f"replayed {observer.spectra} spectra, {observer.finished} finished experiments"
              + (f" to {save}" if save else ""), highlight=False)


@app.command()
def validate(files: Annotated[list[Path], typer.Argument(help="scenario files")]) -> None:
    """Check scenario files; every problem names its file, field and value."""
    bad = 0
    for f in files:
        try:
            s = load(f)
            for dtype in s.devices:
                lab.load_driver(s, dtype, dtype)
            lab.make_planner(s)
            lab.make_scheduler(s)
        except TwinError as exc:
            bad += 1
            err.print(f"[red]✗[/] {exc}", highlight=False)
        else:
            console.print(f"[green]✓[/] {f}")
    if bad:
        raise typer.Exit(2)


@app.command()
def schema() -> None:
    """Print the JSON Schema of scenario files (for editors)."""
    print(json.dumps(json_schema(), indent=2))


@app.command()
def report(journal: Annotated[Path, typer.Argument(help="a run's journal, runs/<run>.db")]) -> None:
    """Print a finished run's summary again from its journal."""
    if not journal.exists():
        _fail(TwinError(f"{journal}: no such journal; runs are written to runs/ by default"))
    data = read_run(journal)
    if "summary" not in data:
        _fail(TwinError(f"{journal}: the run has no summary (it was killed before it could write one)"))
    render_summary(Summary.from_dict(data["summary"]), console)


@app.command()
def devices() -> None:
    """List the installed device drivers: name, where from, package and version, capabilities."""
    from rich.table import Table

    table = Table("driver", "class", "package", "version", "runs")
    for name, ep in sorted(plugins.installed("devices").items()):
        try:
            caps = getattr(ep.load(), "capabilities", None)
            runs = ", ".join(sorted(caps)) if isinstance(caps, (set, frozenset)) else "what options.steps says"
        except Exception as exc:  # a broken plugin is listed, not fatal
            runs = f"[red]failed to load: {exc}[/]"
        table.add_row(name, ep.value, ep.dist.name if ep.dist else "?", ep.dist.version if ep.dist else "?", runs)
    console.print(table)


@app.command()
def train(
    scenario: Annotated[Path, typer.Argument(help="the scenario to train in, e.g. scenarios/quantum_dots.yaml")],
    out: Annotated[Path, typer.Option(help="where to save the policy (.zip, with a .json beside it)")],
    agent: Annotated[str, typer.Option(help="scheduler (the rl scheduler), planner (the rl planner), "
                                            "controller or controller-residual (the reactor's heater)")] = "scheduler",
    steps: Annotated[int, typer.Option(help="environment steps")] = 200_000,
    seed: Annotated[int, typer.Option(help="training seed")] = 0,
    envs: Annotated[int, typer.Option(help="environments stepped together")] = 4,
    eval_every: Annotated[int, typer.Option(help="evaluate (and keep the best policy) every this many steps")] = 20_000,
    save: Annotated[Optional[Path], typer.Option(help="also record the evaluation curve to Rerun, e.g. curve.rrd")] = None,
    viewer: Annotated[bool, typer.Option(help="show the evaluation curve live in the Rerun viewer")] = False,
) -> None:
    """Train an agent in the twin; the evaluation curve is printed as it goes (and recorded to Rerun if asked)."""
    try:
        s = lab.prepare(scenario)
        trainer = plugins.load("trainers", agent)
    except TwinError as exc:
        _fail(exc)
    recording = None
    if save or viewer:
        from twin.recorder import log_curve, open_recording

        recording = open_recording(f"train-{agent}-{s.name}", save=save, viewer=viewer, campaign_layout=False)
        for message in recording.messages:
            err.print(message, highlight=False)
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=err)

    def report(done: int, result: dict | None) -> None:
        progress.update(bar, completed=done)
        if result:
            fields = "  ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                               for k, v in result.items() if k != "policy")
            if recording is not None:
                numbers = {k: v for k, v in result.items() if isinstance(v, (int, float))}
                log_curve(recording, done, numbers, f"training/{result['policy'].split(':')[0].replace(' ', '_')}")
            progress.console.print(f"{done:>9,} steps  {result['policy']:14} {fields}", highlight=False)

    with progress:
        bar = progress.add_task(f"training the {agent} on {s.name}", total=steps)
        try:
            path = trainer(s, steps, out, seed=seed, envs=envs, eval_every=eval_every, on_progress=report)
        except (TwinError, ValueError) as exc:
            _fail(TwinError(str(exc)))
        except KeyboardInterrupt:
            progress.stop()
            kept = out.with_suffix(".zip")
            err.print(f"interrupted; {'the best policy so far is ' + str(kept) if kept.exists() else 'no policy saved yet'}",
                      highlight=False)
            raise typer.Exit(130) from None
        finally:
            if recording is not None:
                recording.close()
    console.print(f"saved {path} (and {path.with_suffix('.json').name})")


@bench_app.command("planners")
def bench_planners(
    scenario: Annotated[Path, typer.Argument(help="a scenario with targets, e.g. scenarios/quantum_dots.yaml")],
    seeds: Annotated[int, typer.Option(help="seeds per planner")] = 20,
    planners: Annotated[str, typer.Option(help="comma-separated; name~seq runs one experiment at a time")] = ",".join(DEFAULT_PLANNERS),
    workers: Annotated[int, typer.Option(help="campaigns run in parallel")] = 2,
    budget: Annotated[Optional[int], typer.Option(help="override the scenario's budget (a larger one censors less)")] = None,
) -> None:
    """Experiments and lab-hours to target (median [IQR]) for each planner over many seeds, vs random."""
    from rich.table import Table

    from twin.planner_bench import HEADER, bench, rows

    names = [p.strip() for p in planners.split(",") if p.strip()]
    try:
        s = lab.prepare(scenario)
        for name in names:
            lab.make_planner(s.model_copy(update={"campaign": s.campaign.model_copy(update={"planner": name.split("~")[0]})}))
    except TwinError as exc:
        _fail(exc)
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        console=err)
    with progress:
        bar = progress.add_task(f"{s.name}: {len(names)} planners × {seeds} seeds", total=len(names) * seeds)
        results = bench(scenario, names, seeds, workers, on_trial=lambda t: progress.advance(bar), budget=budget)
    table = Table(title=f"{s.name} — {seeds} seeds, budget {budget or s.campaign.budget}, "
                        f"{s.campaign.max_in_flight} in the lab; medians [IQR]; ≥: censored by the budget",
                  title_justify="left")
    for h in HEADER:
        table.add_column(h)
    for row in rows(results):
        table.add_row(*row)
    console.print(table)


@bench_app.command("schedulers")
def bench_schedulers(
    scenario: Annotated[Path, typer.Argument(help="a scenario, e.g. scenarios/flaky_lab.yaml or scenarios/jobshop.yaml")],
    seeds: Annotated[int, typer.Option(help="seeds per scheduler (a deterministic job shop runs once)")] = 20,
    schedulers: Annotated[str, typer.Option(help="comma-separated: rules, cp-sat, rl:POLICY.zip")] = "fifo,spt,mwkr,least-loaded,oldest-sample",
    jobshop: Annotated[Optional[str], typer.Option(help="job-shop files to run instead of the scenario's, comma-separated "
                                                       "(e.g. jobshop/la01.txt,jobshop/ft10.txt)")] = None,
    workers: Annotated[int, typer.Option(help="campaigns run in parallel")] = 2,
    budget: Annotated[Optional[int], typer.Option(help="override the scenario's budget")] = None,
    set_: Annotated[Optional[list[str]], typer.Option("--set", help="override a scenario field, e.g. "
                                                      "devices.reactor.instances=1 (another lab shape); repeatable")] = None,
) -> None:
    """Makespan, gap to the CP-SAT bound, utilisation, degraded and lost samples, decision latency per scheduler."""
    from rich.table import Table

    from twin.scheduler_bench import HEADER, bench, bound, load_variant, rows

    names = [p.strip() for p in schedulers.split(",") if p.strip()]
    files = [f.strip() for f in jobshop.split(",")] if jobshop else [None]
    for file in files:
        try:
            s = load_variant(scenario, file, budget, _assignments(set_ or []))
            for name in names:
                lab.make_scheduler(s, name)
        except TwinError as exc:
            _fail(exc)
        optimum = bound(s)
        title = f"{Path(file).stem if file else s.name}"
        progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TimeElapsedColumn(), console=err)
        with progress:
            bar = progress.add_task(f"{title}: {len(names)} schedulers", total=len(names) * (1 if s.jobshop else seeds))
            results = bench(s, names, seeds, workers, on_run=lambda r: progress.advance(bar))
        runs = len(next(iter(results.values())))
        table = Table(title=f"{title} — {runs} run(s) per scheduler" + (f"; CP-SAT bound {optimum:.0f} lab-s" if optimum else ""),
                      title_justify="left")
        for h in HEADER:
            table.add_column(h)
        for row in rows(results, optimum, 1.0 if s.jobshop else 3600.0):
            table.add_row(*row)
        console.print(table)


def _assignments(items: list[str]) -> dict:
    """``["a.b=1", "c=x"]`` → ``{"a.b": 1, "c": "x"}`` (values read as YAML)."""
    import yaml

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            _fail(TwinError(f"--set {item!r}: expected FIELD=VALUE, e.g. devices.reactor.instances=1"))
        out[key.strip()] = yaml.safe_load(value)
    return out


@device_app.command("serve")
def device_serve(
    scenario: Annotated[Path, typer.Argument(help="the scenario the device belongs to")],
    name: Annotated[str, typer.Option("--id", help="the device instance, e.g. spectrometer-2")],
    connect: Annotated[list[str], typer.Option(help="a Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447")],
    clock: Annotated[str, typer.Option(help="scaled | wall (the lab's clock)")] = "wall",
    speed: Annotated[float, typer.Option(help="lab seconds per wall second")] = 1.0,
) -> None:
    """Serve one device actor of a scenario in this process until SIGINT/SIGTERM."""
    from twin.serve import serve_device

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        serve_device(scenario, name, connect, clock, speed)
    except TwinError as exc:
        _fail(exc)



@driver_app.command("new")
def driver_new(
    name: Annotated[str, typer.Argument(help="the driver's name, e.g. acme-hplc (also the package's)")],
    directory: Annotated[Path, typer.Option("--dir", help="where to create the package")] = Path("."),
) -> None:
    """Scaffold a pip-installable driver package (entry point, driver, test, demo scenario)."""
    from twin.scaffold import scaffold

    try:
        root = scaffold(name, directory)
    except TwinError as exc:
        _fail(exc)
    console.print(f"created {root}\n  next: pip install -e {root}  (then `twin devices` lists {name})\n"
                  f"        python -m pytest {root / 'tests'}", highlight=False)


@app.command()
def router(
    listen: Annotated[list[str], typer.Option(help="endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447")],
    lease_ms: Annotated[int, typer.Option(help="how long a silent peer is kept, ms (a frozen process is seen after it)")] = 1000,
    zenoh_config: Annotated[Optional[list[str]], typer.Option("--config", help="extra Zenoh config PATH=JSON5 "
                                                                "(TLS etc.), e.g. transport/link/tls/root_ca_certificate=\"ca.pem\"")] = None,
) -> None:
    """A Zenoh router for a lab spread over processes or hosts (devices and labs --connect to it)."""
    import json as _json

    from twin.bus.zenoh_bus import run_router

    extra = {}
    for item in zenoh_config or []:
        path, sep, value = item.partition("=")
        if not sep:
            _fail(TwinError(f"--config {item!r}: expected PATH=JSON5, e.g. transport/link/tx/lease=2000"))
        try:
            extra[path] = _json.loads(value)
        except ValueError:
            extra[path] = value
    try:
        run_router(listen, lease_ms, extra, ready=lambda line: print(line, flush=True))
    except TwinError as exc:
        _fail(exc)


@scheduler_app.command("serve")
def scheduler_serve(
    scenario: Annotated[Path, typer.Argument(help="the scenario of the lab to schedule")],
    scheduler: Annotated[str, typer.Option(help="rl:POLICY.zip or a rule (fifo, spt, mwkr, least-loaded, ...)")],
    connect: Annotated[list[str], typer.Option(help="a Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447")],
    clock: Annotated[str, typer.Option(help="scaled | wall (the lab's clock)")] = "wall",
    speed: Annotated[float, typer.Option(help="lab seconds per wall second")] = 1.0,
) -> None:
    """Serve scheduling decisions to a lab whose campaign.scheduler is `remote`, until SIGINT/SIGTERM."""
    from twin.serve import serve_scheduler

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        serve_scheduler(scenario, scheduler, connect, clock, speed)
    except TwinError as exc:
        _fail(exc)
