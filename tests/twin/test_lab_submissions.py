"""A lab that serves (`twin lab serve`) and the campaigns submitted to it: over Zenoh, hostile ones, and those
that name code for the lab to import."""

import json
import re
from pathlib import Path

import pytest

from tests.conftest import twin_cli
from tests.twin.shared_labs import LAB, ROOT, assert_one_step_at_a_time, events, kill_all, lines_until
from twin.runtime.lab import prepare
from twin.scenario import load



@pytest.mark.process
def test_twin_lab_serve_takes_campaigns_from_twin_submit_and_lists_them(tmp_path):
    """A served lab starts empty; two campaigns are submitted over Zenoh, `twin ctl status` lists them, one is
    paused by name; SIGTERM ends the lab with each campaign's summary and journal."""
    import signal
    import socket
    import os
    import subprocess
    import sys

    import yaml
    from tests.rrd import read_rrd
    from twin.campaign.journal_read import read_run

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    raw = yaml.safe_load(LAB.read_text())
    campaigns = raw.pop("campaigns")
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(raw))
    for c, budget in zip(campaigns, (4, 3)):
        c["campaign"].update(budget=budget, planner="random", stop_on_target=False)
        (tmp_path / f"{c['name']}.yaml").write_text(yaml.safe_dump(c))
    lab = subprocess.Popen([sys.executable, "-m", "twin", "lab", "serve", str(tmp_path / "lab.yaml"), "--listen",
                            f"tcp/127.0.0.1:{port}", "--speed", "3000", "--journal", str(tmp_path / "runs")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True,
                           env={**os.environ, "COLUMNS": "200"})  # its summary's cells unfolded, whatever they hold
    connect = ["--lab", "shared", "--connect", f"tcp/127.0.0.1:{port}"]
    watcher = None

    def ctl(*args):
        return twin_cli(*args, *connect, columns=100)

    try:
        line = lab.stderr.readline()
        assert "serving lab shared" in line, line + lab.stderr.read() if lab.poll() is not None else line
        assert f"`twin submit CAMPAIGN.yaml --lab shared --connect tcp/127.0.0.1:{port}` adds one" in line, line
        assert ctl("submit", str(tmp_path / "dots.yaml"), "--as", "qd-group").exit_code == 0
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            own = sock.getsockname()[1]
        (tmp_path / "again").mkdir()  # an earlier lab's journals, where the second serve is told to write
        (tmp_path / "again" / "lab.inputs").write_bytes(b"an earlier lab's inputs")
        second = subprocess.run([sys.executable, "-m", "twin", "lab", "serve", str(tmp_path / "lab.yaml"), "--listen",
                                 f"tcp/127.0.0.1:{own}", "--connect", f"tcp/127.0.0.1:{port}", "--journal",
                                 str(tmp_path / "again")],
                                capture_output=True, text=True, cwd=ROOT, timeout=60)  # the same lab served twice
        assert second.returncode == 2 and "lab 'shared' already has a campaign running" in second.stderr, second.stderr
        # refused before it wrote anything: the earlier journals stay as they were
        assert [p.name for p in (tmp_path / "again").iterdir()] == ["lab.inputs"]
        assert (tmp_path / "again" / "lab.inputs").read_bytes() == b"an earlier lab's inputs"
        watcher = subprocess.Popen([sys.executable, "-m", "twin", "watch", "--lab", "shared", "--connect",
                                    f"tcp/127.0.0.1:{port}", "--save", str(tmp_path / "w.rrd"), "--follow"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT, text=True)
        assert "watching lab" in watcher.stdout.readline()
        sub = subprocess.run([sys.executable, "-m", "twin", "submit", "-", *connect], cwd=ROOT, capture_output=True,
                             text=True, timeout=60, input=(tmp_path / "catalyst.yaml").read_text())  # stdin, read once
        assert sub.returncode == 0 and "campaign catalyst started on lab shared" in sub.stdout, sub.stderr
        again = ctl("submit", str(tmp_path / "dots.yaml"))
        assert again.exit_code == 1 and "has a campaign 'dots' already" in again.output
        (tmp_path / "bare.yaml").write_text("name: bare\nworkflow: [{step: measure, device: spectrometer}]\n")
        bare = ctl("submit", str(tmp_path / "bare.yaml"))  # no chemistry, and the lab file has none either
        said = " ".join(bare.output.split())
        assert bare.exit_code == 1 and "refused: campaign bare: 2 problems" in said, said  # both at once
        assert "chemistry.model: none given" in said and "give chemistry.model, one of ['bandgap'" in said, said
        assert "campaign.planner: chemistry.parameters: empty, and planner 'random' proposes values" in said, said
        listed = ctl("ctl", "status")
        assert listed.exit_code == 0 and "dots" in listed.output and "catalyst" in listed.output, listed.output
        assert "each campaign schedules its own steps, in turns" in " ".join(listed.output.split())
        both = ctl("ctl", "pause")
        assert both.exit_code == 1 and "name one with --campaign" in both.output
        paused = ctl("ctl", "pause", "--campaign", "catalyst", "--as", "alice")
        assert paused.exit_code == 0 and "paused" in paused.output, paused.output
        # the campaign's own hours, and the lab's: it started later than the lab
        started = float(re.search(r"started on lab shared at lab ([\d.]+) h", sub.stdout)[1])
        own, at = map(float, re.search(r"at ([\d.]+) h into the campaign \(lab ([\d.]+) h\)", paused.stdout).groups())
        assert at - own == pytest.approx(started, abs=0.05) and started > 0.01, (sub.stdout, paused.stdout)
        assert ctl("ctl", "resume", "--campaign", "catalyst").exit_code == 0
        assert "name one with --campaign (dots, catalyst)" in ctl("ctl", "wait").output
        for name, budget in (("catalyst", 3), ("dots", 4)):  # a script's way to wait for a campaign's end
            waited = ctl("ctl", "wait", "--campaign", name)
            ended = re.match(rf"campaign {name} ended: (\d+) done, (\d+) abandoned", waited.stdout)
            assert waited.exit_code == 0 and ended and int(ended[1]) + int(ended[2]) == budget, waited.output
        assert {c["state"] for c in json.loads(ctl("ctl", "status", "--json").output)["campaigns"]} == {"ended"}
        late = yaml.safe_load((tmp_path / "catalyst.yaml").read_text())
        late["name"], late["campaign"]["budget"] = "late", 1
        late["workflow"] = [w for w in late["workflow"] if w["step"] != "react"]  # no experiment gets through
        (tmp_path / "late.yaml").write_text(yaml.safe_dump(late))
        waited = ctl("submit", str(tmp_path / "late.yaml"), "--wait")  # submitted, and its end waited for
        assert waited.exit_code == 0 and "campaign late ended: " in waited.stdout, waited.output
        assert "campaign late: 0 done" in waited.stderr
        said = " ".join(waited.stderr.split())  # the trial's warning, with the command that stops it
        assert "! campaign late: warning: workflow: 3 trial experiments on the twin" in said, said
        assert f"`twin ctl stop --lab shared --campaign late --connect tcp/127.0.0.1:{port}` stops it" in said, said
        lab.send_signal(signal.SIGTERM)
        out, err = lab.communicate(timeout=60)
        lines_until(watcher.stdout, {"campaign dots ended: 4 experiments", "campaign catalyst ended: 3 experiments"})
        watcher.send_signal(signal.SIGTERM)
        _, watch_err = watcher.communicate(timeout=60)
    finally:
        kill_all(lab, watcher)
    assert lab.returncode == 0, err[-2000:]
    assert watcher.returncode == 0, watch_err[-2000:]
    drawn = read_rrd(tmp_path / "w.rrd")  # a campaign submitted after the watcher joined has its tab too
    for name, budget in (("dots", 4), ("catalyst", 3)):
        assert drawn[f"campaigns/{name}/campaign/finished"][-1]["Scalars:scalars"][0] == budget, name
        assert len(drawn[f"campaigns/{name}/summary"]) == 1, name
    assert {p.split("/")[1] for p in drawn if p.startswith("devices/")} == {
        "synthesiser-1", "synthesiser-2", "reactor", "spectrometer"}
    assert "dots (quantum-dot" in out and "catalyst" in out
    runs = tmp_path / "runs"
    for name, budget in (("dots", 4), ("catalyst", 3)):
        summary = read_run(runs / f"{name}.db")["summary"]
        assert summary["done"] + summary["abandoned"] == budget == summary["proposed"]
    events_ = [e[1] for e in events(runs / "catalyst.db", "operator.pause", "operator.resume", "campaign.submitted")]
    assert events_[0] == "campaign.submitted" and "operator.pause" in events_ and "operator.resume" in events_
    assert_one_step_at_a_time(runs)


def test_hostile_submissions_are_refused_with_the_reason_and_the_lab_goes_on(tmp_path):
    """What `twin submit` could be sent by anyone with the operator's key: every bad one is answered with why,
    and the lab keeps serving the campaign it has."""
    import asyncio

    from twin.runtime.shared_run import serve_lab

    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory",
                overrides={"campaigns.0.campaign.budget": 2, "campaigns.0.campaign.planner": "random",
                           "campaigns": [load(LAB).campaigns[0].model_dump(exclude_none=True)],
                           "orchestrator.lab_scheduler": "fair-share"}, lab_only=True)
    def by_module(name: str, field: str, spec: str) -> bytes:  # a campaign valid but for naming a module to import
        c = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
        c["name"], c["campaign"][field] = name, spec
        return json.dumps({"file": json.dumps(c)}).encode()

    def with_options(name: str, planner: str, options: dict) -> bytes:  # a campaign naming a file of the lab's host
        c = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
        c["name"], c["campaign"]["planner"], c["campaign"]["planner_options"] = name, planner, options
        return json.dumps({"file": json.dumps(c)}).encode()

    def with_chemistry(name: str, options: dict) -> bytes:  # a chemistry model given a file of the lab's host
        c = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
        c["name"], c["chemistry"]["options"] = name, options
        return json.dumps({"file": json.dumps(c)}).encode()

    secret = tmp_path / "secret.txt"  # outside the folder the lab serves from (the tests' working directory)
    secret.write_text("the-first-line-is-a-secret\n")
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{k}: &{k} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, k in zip("abcdefg", "bcdefgh"))
    hostile = {
        b"not json": "not JSON",
        b"[1, 2]": "not a JSON object",
        json.dumps({"file": 42}).encode(): "give the text of a campaign file",
        json.dumps({"file": "name: [unclosed"}).encode(): "not valid YAML",
        json.dumps({"file": bomb}).encode(): "values",
        json.dumps({"file": "name: x\nbudget: 3\n"}).encode(): "budget: unknown field",
        json.dumps({"file": "name: dots\n"}).encode(): "has a campaign 'dots' already",
        json.dumps({"file": "name: y\nafter: dots\n"}).encode(): "after / start_h",
        json.dumps({"file": "name: z\nworkflow: [{step: melt, device: furnace}]\n"}).encode(): "furnace",
        json.dumps({"file": "name: w\nworkflow: [{step: melt, device: synthesiser}]\n"}).encode():
            "campaign w: 1 problem\n  - workflow.0.step: device type 'synthesiser' does not run 'melt'",
        by_module("m", "scheduler", "tests.twin.test_bad_schedulers:Patient"):
            "campaign.scheduler: 'tests.twin.test_bad_schedulers:Patient' is a module path, which the lab would import",
        by_module("n", "planner", "antigravity:Planner"): "campaign.planner: 'antigravity:Planner' is a module path",
        b"{" + b" " * (1 << 21) + b"}": "bytes; at most",
        with_options("p", f"rl:{secret}", {}): f"campaign.planner: '{secret}' is outside the folder the lab serves",
        with_options("q", "route", {"stock": str(secret)}): "campaign.planner_options.stock: ",
        with_options("r", "route", {"templates": "../../../../../../../../etc/hostname"}): "outside the folder",
        with_chemistry("c", {"data": str(secret)}): "chemistry.options.data: ",
        with_options("plate", "fixed", {"proposals": [{"params": {"concentration_mm": 1000, "temperature_c": 250,
                                                                  "time_s": 100}}]}):
            "campaign plate: 1 problem\n  - campaign.planner_options.proposals.0: concentration_mm = 1000 is outside",
    }
    answers: dict = {}

    def started(lab) -> None:
        async def ask() -> None:
            for payload in hostile:
                answers[payload] = json.loads(await lab.desk.serve("labtwin/shared/control/submit", payload))
            answers["status"] = lab.status()
            lab.stop("test over")
        asyncio.ensure_future(ask())

    out = serve_lab(s, tmp_path, handle_signals=False, on_start=started)
    assert answers["status"]["scheduler"] == "fair-share"  # twin ctl status says who decides
    for payload, words in hostile.items():
        answer = answers[payload]
        assert answer["ok"] is False and words in answer["error"], (payload[:60], answer)
        assert "the-first-line-is-a-secret" not in answer["error"]  # a route planner's stock said its first line
    assert list(out.campaigns) == ["dots"] and sorted(p.stem for p in tmp_path.glob("*.db")) == ["dots"]


@pytest.mark.parametrize("trust", [False, True])
def test_a_submitted_campaign_names_a_module_only_if_the_lab_file_does_or_the_lab_trusts_modules(tmp_path, trust):
    """A module path in a submitted campaign is code the lab imports for whoever submitted it: taken when the lab
    file names the same one, or when the lab is served with --trust-modules, and refused otherwise."""
    import asyncio

    from twin.runtime.shared_run import serve_lab

    first = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
    first["campaign"].update(budget=2, planner="random", scheduler="agents.schedulers:MwkrScheduler")
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", overrides={"campaigns": [first]}, lab_only=True)

    def submission(name: str, scheduler: str) -> bytes:
        c = {**first, "name": name, "campaign": {**first["campaign"], "scheduler": scheduler}}
        return json.dumps({"file": json.dumps(c)}).encode()

    answers: dict = {}

    def started(lab) -> None:
        async def ask() -> None:
            for name, scheduler in (("same", "agents.schedulers:MwkrScheduler"),
                                    ("other", "agents.schedulers:SptScheduler")):
                answers[name] = json.loads(await lab.desk.serve("labtwin/shared/control/submit",
                                                                submission(name, scheduler)))
            lab.stop("test over")
        asyncio.ensure_future(ask())

    serve_lab(s, tmp_path, handle_signals=False, on_start=started, trust_modules=trust)
    assert answers["same"]["ok"] is True, answers["same"]
    if trust:
        assert answers["other"]["ok"] is True, answers["other"]
    else:
        assert answers["other"]["ok"] is False and "--trust-modules" in answers["other"]["error"]
    assert (tmp_path / "other.db").exists() == trust
    from twin.campaign.journal_read import read_run

    assert read_run(tmp_path / "lab.inputs")["trust_modules"] is trust  # what `twin resume` serves on with


def test_a_module_the_lab_files_own_campaign_section_names_is_the_lab_files_too(tmp_path):
    """A lab of no campaigns whose `campaign:` section names a scheduler by module path refused every submitted
    campaign that inherited it, saying it takes "the ones the lab file names" — which it was."""
    import asyncio

    from twin.runtime.shared_run import serve_lab

    first = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
    first["campaign"].update(budget=2, planner="random")
    first["campaign"].pop("scheduler", None)
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", lab_only=True,
                overrides={"campaigns": [], "campaign.scheduler": "agents.schedulers:MwkrScheduler"})
    answers: dict = {}

    def started(lab) -> None:
        async def ask() -> None:
            for name, scheduler in (("inherits", None), ("names", "agents.schedulers:MwkrScheduler"),
                                    ("other", "agents.schedulers:SptScheduler")):
                c = {**first, "name": name, "campaign": {**first["campaign"],
                                                         **({"scheduler": scheduler} if scheduler else {})}}
                answers[name] = json.loads(await lab.desk.serve("labtwin/shared/control/submit",
                                                                json.dumps({"file": json.dumps(c)}).encode()))
            lab.stop("test over")
        asyncio.ensure_future(ask())

    serve_lab(s, tmp_path, handle_signals=False, on_start=started)
    assert answers["inherits"]["ok"] is True and answers["names"]["ok"] is True, answers
    assert answers["other"]["ok"] is False and "--trust-modules" in answers["other"]["error"]


def test_a_submitted_campaign_may_name_a_file_outside_the_labs_folder_that_the_lab_file_names(tmp_path):
    """A policy outside the folder the lab serves from is the lab's own when its file names it: a submission may
    name that one, and no other outside it."""
    import asyncio
    import shutil

    from twin.runtime.shared_run import serve_lab

    for name in ("qd.zip", "qd.json", "other.zip", "other.json"):  # outside the tests' working directory
        shutil.copy(ROOT / "agents" / "policies" / f"quantum_dots{Path(name).suffix}", tmp_path / name)
    first = load(LAB).campaigns[0].model_dump(mode="json", exclude_none=True)
    first["campaign"].update(budget=1, planner=f"rl:{tmp_path / 'qd.zip'}")
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", overrides={"campaigns": [first]}, lab_only=True)

    def submission(name: str, policy: str) -> bytes:
        c = {**first, "name": name, "campaign": {**first["campaign"], "planner": f"rl:{policy}"}}
        return json.dumps({"file": json.dumps(c)}).encode()

    answers: dict = {}

    def started(lab) -> None:
        async def ask() -> None:
            for name, policy in (("same", tmp_path / "qd.zip"), ("other", tmp_path / "other.zip")):
                answers[name] = json.loads(await lab.desk.serve("labtwin/shared/control/submit",
                                                                submission(name, str(policy))))
            lab.stop("test over")
        asyncio.ensure_future(ask())

    serve_lab(s, tmp_path / "journals", handle_signals=False, on_start=started)
    assert answers["same"]["ok"] is True, answers["same"]
    assert answers["other"]["ok"] is False and "is outside the folder the lab serves from" in answers["other"]["error"]


def test_a_submitted_campaign_no_experiment_gets_through_is_warned_of_in_the_answer(tmp_path):
    """A live lab's own file is tried on the twin before the lab starts; a campaign submitted to it was not, and
    its every experiment was abandoned at its last step, unseen by whoever submitted it. The answer to `twin submit`
    now says what `twin validate` would: the trial's warning, with the command that stops the campaign."""
    import asyncio

    from twin.runtime.shared_run import serve_lab

    first = load(LAB).campaigns[1].model_dump(mode="json", exclude_none=True)  # catalyst: prepare, react, measure
    first["campaign"].update(budget=2, planner="random")
    s = prepare(LAB, clock="scaled", speed=50_000, bus="memory", overrides={"campaigns": [first]}, lab_only=True)
    unreacted = {**first, "name": "unreacted", "workflow": [w for w in first["workflow"] if w["step"] != "react"]}
    fine = {**first, "name": "fine"}
    aimless = {**first, "name": "aimless", "chemistry": {**first["chemistry"], "targets": []},
               "campaign": {**first["campaign"], "planner": "gp-bo"}}  # what the checks warn of comes back too
    answers: dict = {}

    def started(lab) -> None:
        async def submit(c: dict) -> dict:
            return json.loads(await lab.desk.serve("labtwin/shared/control/submit",
                                                   json.dumps({"file": json.dumps(c)}).encode()))

        async def ask() -> None:  # at once: the second 'fine' is told the name is taken once it has been tried
            said = await asyncio.gather(*(submit(c) for c in (unreacted, fine, fine)))
            answers.update(zip(("unreacted", "fine", "fine again"), said))
            answers["aimless"] = await submit(aimless)
            lab.stop("test over")
        asyncio.ensure_future(ask())

    serve_lab(s, tmp_path, handle_signals=False, on_start=started)
    warned = answers["unreacted"]
    assert warned["ok"] is True and len(warned["warnings"]) == 1, warned
    assert "3 trial experiments on the twin" in warned["warnings"][0]
    assert "cannot measure a sample of kind 'feed'" in warned["warnings"][0]
    assert warned["warnings"][0].endswith("`twin ctl stop --campaign unreacted` stops it")
    assert answers["fine"]["ok"] is True and answers["fine"]["warnings"] == []
    from twin.campaign.journal_read import read_events

    submitted = [e for e in read_events(tmp_path / "unreacted.db") if e["kind"] == "campaign.submitted"]
    assert json.loads(submitted[0]["detail"])["warnings"] == warned["warnings"]  # kept in its journal too
    again = answers["fine again"]
    assert again["ok"] is False and "the lab has a campaign 'fine' already" in again["error"], again
    aimed = answers["aimless"]
    assert aimed["ok"] is True and len(aimed["warnings"]) == 1, aimed
    assert aimed["warnings"][0].startswith("chemistry.targets: none, and planner 'gp-bo' chooses each experiment")
    assert sorted(p.stem for p in tmp_path.glob("*.db")) == ["aimless", "catalyst", "fine", "unreacted"]
