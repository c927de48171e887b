"""`twin train`: training agents in the twin, the evaluation curve as it goes, and what was kept."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from twin.core.printable import shell_word
from twin.core import plugins
from twin.cli.common import app, assignments, bar_progress, console, err, _fail, recording_file, writable
from twin.cli.stopping import exit_status, sigterm_unwinds, stopped_by
from twin.core.errors import TwinError
from twin.core.whole_files import kept_from_others

if TYPE_CHECKING:  # the commands import the runtime when they run: twin ctl or router need none of it
    from twin.scenario import Scenario


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
    where, policy = shell_word(scenario), shell_word(f"{rule},rl:{path}")
    if s.campaigns:
        compare = f"in each campaign of the lab: twin whatif {where} --schedulers {policy}"
    elif s.jobshop is not None:
        compare = f"on shops it never trained on: twin bench schedulers {where} --jobshop DIR --schedulers {policy}"
    else:
        compare = (f"on the lab's variants, 40 paired seeds: twin bench schedulers {where} --shapes --seeds 40 "
                   f"--schedulers {policy}")
    said = (f"kept the round at {best['steps']:,} steps: score {best['score']:.3f}, its objective ÷ the best rule's "
            f"({rule}) on the evaluation runs (below 1 is better): {verdict}. Compare them {compare}")
    solver = best.get("vs cp-sat")
    if isinstance(solver, (int, float)) and solver > 1.03 and not s.campaigns and s.jobshop is None:
        # a learnt policy imitates a rule there (cp-sat teaches job shops only): the better schedules exist
        said += (f". CP-SAT, scheduling the lab online, did {100 * (1 - 1 / solver):.0f} % better than it on the "
                 f"evaluation run (vs cp-sat {solver:.2f}): compare it too (--schedulers "
                 f"{shell_word(f'{rule},cp-sat,rl:{path}')}), or run the "
                 "lab with campaign.scheduler: cp-sat (up to campaign.scheduler_options.time_limit_s of wall time "
                 "a decision)")
    return said
