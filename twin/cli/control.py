"""``twin ctl``: an operator's commands to a running campaign, over the lab's bus."""

from __future__ import annotations

import getpass
import json
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from rich.markup import escape

from twin.cli.common import _fail, app, check_lab_name, command_group, console, err, narrow_table, print_table
from twin.core.counts import counted, quantity
from twin.core.errors import TwinError

ctl_app = command_group("Operate a running campaign: status, pause, resume, abort, retry, stop; answer its "
                        "questions, refill its consumables, confirm human steps (pending, answer, refill, confirm).")
app.add_typer(ctl_app, name="ctl")

Lab = Annotated[str, typer.Option("--lab", callback=check_lab_name,
                                  help="the lab (the scenario's `lab` field)")]
Connect = Annotated[list[str], typer.Option(metavar="ENDPOINT",
                                            help="a Zenoh endpoint of the lab, e.g. tcp/127.0.0.1:7447 (the "
                                                 "campaign's --listen, or the lab's router)")]
Security = Annotated[Optional[Path], typer.Option(help="the lab's security directory: ask as its operator")]
Who = Annotated[Optional[str], typer.Option("--as", help="the name the journal records (default: your login)")]
Reason = Annotated[str, typer.Option(help="why, for the journal")]
AsJson = Annotated[bool, typer.Option("--json", help="print the campaign's answer as JSON")]
CampaignOpt = Annotated[Optional[str], typer.Option(help="a lab that several campaigns share (twin lab serve): "
                                                         "which campaign")]


def _who(name: str | None) -> str:
    if name:
        return name
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "operator"


def _send(command: str, lab: str, connect: list[str], security: Path | None, as_json: bool,
          campaign: str | None = None, **body: Any) -> dict:
    from twin.tools.control import request

    if campaign is not None:
        body["campaign"] = campaign
    try:
        answer = request(lab, command, body, list(connect), str(security) if security else None)
    except TwinError as exc:
        _fail(exc)
    if as_json:
        print(json.dumps(answer, indent=2))
    if not answer.get("ok"):
        if not as_json:
            err.print(f"[bold red]refused:[/] {escape(str(answer.get('error')))}", highlight=False, markup=True)
        raise typer.Exit(1)
    return answer


def _when(hours: float, status: dict) -> str:
    """'lab 0.44 h' for a campaign alone on its lab; for one of a lab's campaigns, which may have started at any
    time of the lab's, its own hours and the lab's."""
    started = status.get("started_lab_hours")
    if started is None:
        return f"lab {hours:.2f} h"
    return f"{hours:.2f} h into the campaign (lab {started + hours:.2f} h)"


def _acted(answer: dict, as_json: bool) -> None:
    if not as_json:
        st = answer["status"]
        console.print(f"{answer['done']} by {answer['who']} at {_when(answer['lab_hours'], st)} — the campaign is "
                      f"{st['state']}", highlight=False, markup=False)


def _lab_status(answer: dict) -> None:
    """A lab that several campaigns share: a row per campaign."""
    one = answer.get("scheduler")
    console.print(f"lab {answer['lab']} at lab {answer['lab_hours']:.2f} h: "
                  f"{counted(len(answer['campaigns']), 'campaign', 'campaigns')}"
                  f"{'; it takes more (twin submit)' if answer['serving'] else ''}; "
                  f"{f'one scheduler for the lab: {one}' if one else 'each campaign schedules its own steps, in turns'}",
                  highlight=False, markup=False)
    table = narrow_table(["campaign", "owner", "prio", "state", "done", "aband.", "in lab", "budget"],
                         caption="twin ctl status --campaign NAME: one campaign in full")
    for c in answer["campaigns"]:
        table.add_row(c["campaign"], c["owner"], str(c["priority"]), c["state"],
                      str(c["done"]), str(c["abandoned"]), str(c["in_progress"]), str(c["budget"]))
    print_table(table)


@ctl_app.command("status")
def ctl_status(lab: Lab, connect: Connect, security: Security = None,
               campaign: CampaignOpt = None, as_json: AsJson = False) -> None:
    """The campaign's state (running / paused by whom / stopping), its experiments, what is in the lab."""
    answer = _send("status", lab, connect, security, as_json, campaign=campaign)
    if as_json:
        return
    if "campaigns" in answer:
        _lab_status(answer)
        return
    st = answer["status"]
    paused = f" by {st['paused_by']}" if st["paused_by"] else ""
    console.print(f"{st['scenario']} (campaign {st['campaign']}, lab {st['lab']}): {st['state']}{paused} at "
                  f"{_when(st['lab_hours'], st)}", highlight=False, markup=False)
    if st.get("stalled"):
        console.print(f"stalled: {st['stalled']} (the lab waits; twin ctl stop, and run it with another scheduler)",
                      style="yellow", highlight=False, markup=False)
    counts = st["experiments"]
    console.print(f"experiments: {counts['done']} done, {counts['abandoned']} abandoned, "
                  f"{counts['pending'] + counts['running']} in progress, of a budget of {st['budget']}",
                  highlight=False, markup=False)
    table = narrow_table(["device", "state", "step", "for lab-s"])
    running, stuck = {r["device"]: r for r in st["in_lab"]}, st.get("stuck") or {}
    for name, state in st["devices"].items():
        r, held = running.get(name), stuck.get(name)
        step = f"{r['task']} #{r['attempt']}" if r else \
            f"{held['task']} #{held['attempt']}: cancelled, still running" if held else ""
        table.add_row(name, state, step, f"{r['for_s']:.0f}" if r else "")
    print_table(table)
    if st.get("consumables"):
        console.print(_stock_table(st["consumables"]))
    if st["ready"] or st["retrying"]:
        console.print(f"waiting for a device: {', '.join(st['ready']) or '-'}; waiting to retry: "
                      f"{', '.join(st['retrying']) or '-'}", highlight=False, markup=False)
    for n, reason in st["abandoned"].items():
        console.print(f"abandoned {n}: {reason}  (twin ctl retry {n})", highlight=False, markup=False)


def _stock_table(stocks: dict[str, dict]) -> Any:
    """Each stock's level, and when it runs out at the rate so far (or what waits for its refill)."""
    table = narrow_table(["stock", "level", "reorder at", "runs out in", "waiting"])
    for name, c in stocks.items():
        out = c.get("runs_out_in_s")
        when = "short" if c["depleted"] else "empty" if c["level"] <= 0 else \
            f"{out / 3600:.1f} lab-h" if out is not None else "-"
        table.add_row(name, quantity(c['level'], c['unit']), f"{c['reorder_at']:g}", when,
                      ", ".join(c["waiting"]) or "")
    return table


@ctl_app.command("pause")
def ctl_pause(lab: Lab, connect: Connect, now: Annotated[bool, typer.Option(
        help="also take the steps in the lab out, to a safe state (they run again after resume)")] = False,
        reason: Reason = "", who: Who = None, security: Security = None,
              campaign: CampaignOpt = None, as_json: AsJson = False) -> None:
    """Stop new dispatch: steps in the lab finish (or, with --now, are cancelled), nothing new starts until resume.
    A paused campaign stays paused across `twin resume`."""
    _acted(_send("pause", lab, connect, security, as_json,
                 campaign=campaign, who=_who(who), now=now, reason=reason), as_json)


@ctl_app.command("resume")
def ctl_resume(lab: Lab, connect: Connect, who: Who = None, security: Security = None, campaign: CampaignOpt = None,
               as_json: AsJson = False) -> None:
    """Let a paused campaign dispatch again."""
    _acted(_send("resume", lab, connect, security, as_json, campaign=campaign, who=_who(who)), as_json)


@ctl_app.command("abort")
def ctl_abort(experiment: Annotated[int, typer.Argument(help="the experiment's number (twin ctl status)")],
              lab: Lab, connect: Connect, reason: Reason = "", who: Who = None, security: Security = None,
              campaign: CampaignOpt = None,
              as_json: AsJson = False) -> None:
    """Abandon one experiment: its step in the lab is cancelled, the journal says who aborted it and why."""
    _acted(_send("abort", lab, connect, security, as_json,
                 campaign=campaign, who=_who(who), experiment=experiment, reason=reason),
           as_json)


@ctl_app.command("retry")
def ctl_retry(experiment: Annotated[int, typer.Argument(help="the experiment's number (twin ctl status)")],
              lab: Lab, connect: Connect, who: Who = None, security: Security = None,
              campaign: CampaignOpt = None, as_json: AsJson = False) -> None:
    """Retry one experiment now: a step waiting out its back-off goes at once; an abandoned experiment runs again
    from the step that failed, with fresh attempts."""
    _acted(_send("retry", lab, connect, security, as_json,
                 campaign=campaign, who=_who(who), experiment=experiment), as_json)


@ctl_app.command("stop")
def ctl_stop(lab: Lab, connect: Connect, reason: Reason = "", who: Who = None, security: Security = None,
             campaign: CampaignOpt = None,
             as_json: AsJson = False) -> None:
    """End the campaign as Ctrl-C would: steps in the lab are cancelled, the rest stays pending in the journal."""
    _acted(_send("stop", lab, connect, security, as_json, campaign=campaign, who=_who(who), reason=reason), as_json)


@ctl_app.command("pending")
def ctl_pending(lab: Lab, connect: Connect, security: Security = None, campaign: CampaignOpt = None,
                as_json: AsJson = False) -> None:
    """The questions waiting for an operator: a failed step, the options, and the default that applies when."""
    answer = _send("status", lab, connect, security, as_json, campaign=campaign)
    if as_json:
        return
    if "campaigns" in answer:
        _fail(TwinError(f"lab {lab} runs {len(answer['campaigns'])} campaigns: name one with --campaign "
                        f"({', '.join(c['campaign'] for c in answer['campaigns'])})"))
    pending = answer["status"]["questions"]
    short = {k: v for k, v in answer["status"]["consumables"].items() if v["depleted"]}
    if not pending and not short and not answer["status"]["human_steps"]:
        console.print("no question is waiting", highlight=False, markup=False)
        return
    for h in answer["status"]["human_steps"]:
        how = f" — {h['instructions']}" if h["instructions"] else ""
        console.print(f"{h['task']}: {h['step']} on {h['device']}{how}, waiting {h['for_s']:.0f} lab-s "
                      f"(twin ctl confirm {h['task']})", highlight=False, markup=False)
    for name, c in short.items():
        who = f"{', '.join(c['waiting'])} wait" if len(c["waiting"]) > 1 else f"{c['waiting'][0]} waits" \
            if c["waiting"] else "nothing waits"
        console.print(f"{name} is short ({quantity(c['level'], c['unit'])} left): {who} for it (twin ctl refill {name} "
                      "[--amount X])", highlight=False, markup=False)
    for q in pending:
        console.print(f"{q['id']}: experiment {q['experiment']}, {q['why']}\n"
                      f"  options: {', '.join(q['options'])}; {q['default']} in {q['default_in_s']:.0f} lab-s unless "
                      f"answered (twin ctl answer {q['id']} OPTION)", highlight=False, markup=False)


@ctl_app.command("answer")
def ctl_answer(question: Annotated[str, typer.Argument(help="the question's id (twin ctl pending), e.g. q3")],
               option: Annotated[str, typer.Argument(help="one of the question's options: retry, another_device, "
                                                          "skip, alternative, abandon")],
               lab: Lab, connect: Connect, who: Who = None, security: Security = None, campaign: CampaignOpt = None,
               as_json: AsJson = False) -> None:
    """Answer a question: the failed step is retried (with fresh attempts, or on another device) or skipped, or
    its experiment abandoned (with `alternative`, the planner proposes one in its place)."""
    _acted(_send("answer", lab, connect, security, as_json,
                 campaign=campaign, who=_who(who), question=question, option=option), as_json)


@ctl_app.command("refill")
def ctl_refill(item: Annotated[str, typer.Argument(help="the consumable, as the scenario names it (an item each "
                                                        "instance holds: ITEM@INSTANCE for one, ITEM for all)")],
               lab: Lab, connect: Connect,
               amount: Annotated[Optional[float], typer.Option(help="how much is added (default: fill to the "
                                                                     "starting level)")] = None,
               who: Who = None, security: Security = None,
               campaign: CampaignOpt = None, as_json: AsJson = False) -> None:
    """Say a consumable was refilled: the steps that waited for it go on."""
    _acted(_send("refill", lab, connect, security, as_json,
                 campaign=campaign, who=_who(who), item=item, amount=amount), as_json)


@ctl_app.command("confirm")
def ctl_confirm(task: Annotated[str, typer.Argument(help="the human step done, e.g. e3s1 (twin ctl pending)")],
                lab: Lab, connect: Connect, who: Who = None, security: Security = None,
                campaign: CampaignOpt = None, as_json: AsJson = False) -> None:
    """Confirm a human step (a device type whose driver is `operator`) is done: the experiment goes on."""
    _acted(_send("confirm", lab, connect, security, as_json, campaign=campaign, who=_who(who), task=task), as_json)


@ctl_app.command("wait")
def ctl_wait(lab: Lab, connect: Connect, security: Security = None, campaign: CampaignOpt = None) -> None:
    """Wait until the campaign has ended, saying how it goes (on stderr); then print its counts. For scripts: exit
    0 when it has ended, 1 if its lab stops answering first, 130 on Ctrl-C (the campaign goes on)."""
    until_ended(lab, list(connect), str(security) if security else None, campaign)


def until_ended(lab: str, connect: list[str], security: str | None, campaign: str | None = None,
                journal: str = "", every_s: float = 1.0) -> None:
    """Ask the lab every ``every_s`` seconds until ``campaign`` (a lab's only one, if not named) has ended; each
    change of its counts is said on stderr, its end on stdout. A campaign run on its own ends with its process:
    its lab no longer answering then is its end."""
    import time

    from twin.tools.control import request

    said, alone = None, False
    journal_said = f"; its journal: {journal}" if journal else ""
    try:
        while True:
            try:
                answer = request(lab, "status", {}, connect, security)
            except TwinError as exc:
                if alone:
                    console.print(f"campaign {campaign} of lab {lab} has ended: its lab no longer answers (twin "
                                  "report on its journal says how it ended)", highlight=False, markup=False)
                    return
                _fail(exc if said is None else TwinError(f"the lab stopped answering while campaign {campaign} ran "
                                                         f"({exc}){journal_said}"))
            if not answer.get("ok"):
                _fail(TwinError(f"lab {lab} refused: {answer.get('error')}"))
            if "campaigns" in answer:
                row, hours = _campaign_row(answer, lab, campaign), answer["lab_hours"]
            else:  # a campaign run on its own
                alone, st = True, answer["status"]
                if campaign not in (None, st["scenario"]):
                    _fail(TwinError(f"lab {lab} runs one campaign, {st['scenario']!r}, not {campaign!r}: leave "
                                    "--campaign out"))
                row = {"campaign": st["scenario"], "done": st["experiments"]["done"],
                       "abandoned": st["experiments"]["abandoned"],
                       "in_progress": st["experiments"]["pending"] + st["experiments"]["running"],
                       "budget": st["budget"], "state": "ended" if st["state"] == "finished" else st["state"]}
                hours = st["lab_hours"]
            campaign = campaign or row["campaign"]
            if row["state"] == "ended":
                met = f"; targets met: {', '.join(row['targets_met'])}" if row.get("targets_met") else ""
                console.print(f"campaign {campaign} ended: {row['done']} done, {row['abandoned']} abandoned"
                              f"{met}{journal_said}", highlight=False, markup=False)
                return
            now = (row["done"], row["abandoned"], row["in_progress"], row["state"])
            if now != said:  # the counts or the state changed (not only the lab's time)
                err.print(f"campaign {campaign}: {row['done']} done, {row['abandoned']} abandoned, "
                          f"{row['in_progress']} in progress, of a budget of {row['budget']} ({row['state']}, lab "
                          f"{hours:.2f} h)", highlight=False, markup=False)
                said = now
            time.sleep(every_s)  # a client's poll of another process, in its user's seconds: no lab clock here
    except KeyboardInterrupt:
        err.print(f"stopped waiting; the campaign goes on in lab {lab} (twin ctl status)", highlight=False,
                  markup=False)
        raise typer.Exit(130) from None


def _campaign_row(answer: dict, lab: str, campaign: str | None) -> dict:
    rows = answer["campaigns"]
    if campaign is None and len(rows) != 1:
        _fail(TwinError(f"lab {lab} runs {len(rows)} campaigns: name one with --campaign "
                        f"({', '.join(c['campaign'] for c in rows) or 'none yet'})"))
    row = next((c for c in rows if campaign is None or c["campaign"] == campaign), None)
    if row is None:
        _fail(TwinError(f"lab {lab} has no campaign {campaign!r} ({', '.join(c['campaign'] for c in rows)})"))
    return row
