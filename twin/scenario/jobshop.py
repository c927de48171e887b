"""Job-shop instances as labs: one device per machine, deterministic durations, no faults.

Two text formats are read, ``#`` starting a comment:

- the standard one (JSPLIB, OR-Library): ``jobs machines``, then one line per
  job of ``machine duration`` pairs in processing order, machines numbered from
  0; lines of words before it (an OR-Library title) are skipped;
- Taillard's: ``jobs machines`` (more numbers on that line are ignored), the
  jobs' durations as a jobs × machines matrix, then the machines they visit in
  that order, numbered from 1 — with or without the ``Times``/``Machines`` labels
  and the line of words above of Taillard's own files.

A file holds one instance, or is a collection: of the standard format as OR-Library's ``jobshop1.txt`` is, each
instance after a line ``instance NAME``; or of Taillard's, as his own files are (``tai15_15.txt``: ten instances,
each under its ``Nb of jobs, Nb of Machines, ...`` line), the k-th named ``STEM-k`` after the file
(``tai15_15-3``). ``jobshop.instance`` names one. Rules of ``+``, ``-``, ``=`` or ``*`` between them are skipped.

One time unit is one lab-second.
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core.counts import counted
from twin.core.errors import ScenarioError
from twin.scenario.files import nearest_file, read_text
from twin.scenario.model import Scenario


@dataclass(frozen=True)
class Instance:
    name: str
    machines: int
    jobs: list[list[tuple[int, int]]]  # per job: (machine, duration) in order


MAX_JOBS, MAX_MACHINES, MAX_DURATION = 1000, 256, 10**7
FORMATS = ("expected 'jobs machines', then per job a line of 'machine duration' pairs with machines from 0, or "
           "Taillard's durations matrix then machines matrix with machines from 1")


_TITLE = re.compile(r"instance\s+(\S+)", re.IGNORECASE)  # OR-Library's title of an instance in a collection
_TAILLARD = re.compile(r"nb\s+of\s+jobs\b", re.IGNORECASE)  # the line above each instance of Taillard's files
_RULE = re.compile(r"[-+=*_~]{3,}")


def _lines(path: Path) -> list[tuple[int, str]]:
    """The file's lines that say something: (line number, text) without comments, blanks and rules."""
    lines = [(i, ln.split("#")[0].strip()) for i, ln in enumerate(read_text(path, "job-shop").splitlines(), 1)]
    return [(i, ln) for i, ln in lines if ln and not _RULE.fullmatch(ln)]


def _titles(lines: list[tuple[int, str]], stem: str) -> list[tuple[int, str]]:
    """Where each instance of a collection starts, and its name: OR-Library's ``instance NAME`` lines, or else
    Taillard's ``Nb of jobs, ...`` lines, the k-th named ``STEM-k``."""
    titles = [(k, m.group(1)) for k, (_, ln) in enumerate(lines) if (m := _TITLE.fullmatch(ln))]
    if titles:
        return titles
    heads = [k for k, (_, ln) in enumerate(lines) if _TAILLARD.match(ln)]
    return [(k, f"{stem}-{n}") for n, k in enumerate(heads, 1)] if len(heads) > 1 else []


def instances(path: str | Path) -> list[str]:
    """The names of the instances a collection holds; [] for a file of one."""
    titles = _titles(_lines(Path(path)), Path(path).stem)
    return [name for _, name in titles] if len(titles) > 1 else []


def _one_of(where: str, lines: list[tuple[int, str]], instance: str | None) -> tuple[list[tuple[int, str]], str | None]:
    """The lines of the instance named ``instance`` (or of the file's only one), and its name if it has one."""
    titles = _titles(lines, Path(where).stem)
    names = [name for _, name in titles]
    listed = ", ".join(names[:12]) + (f", ... ({len(names)} in all)" if len(names) > 12 else "")
    if instance is None:
        if len(titles) > 1:
            raise ScenarioError(where, [f"holds {len(titles)} instances ({listed}): name one with jobshop.instance "
                                        f"(--set jobshop.instance={names[0]}), or give each its own file"])
        return lines, None
    if instance not in names:
        held = f"it holds {listed}" if names else "it holds one instance, with no 'instance NAME' line: leave " \
                                                  "jobshop.instance out"
        raise ScenarioError(where, [f"jobshop.instance: no instance {instance!r} in the file; {held}"])
    k = names.index(instance)
    end = titles[k + 1][0] if k + 1 < len(titles) else len(lines)
    return lines[titles[k][0] + 1:end], instance


def read(path: str | Path, instance: str | None = None) -> Instance:
    """An instance in either format of the module's docstring (``instance``: which one of a collection); an error
    names the file and the line."""
    path = Path(path)
    where = str(path)
    lines = _lines(path)
    if not lines:
        raise ScenarioError(where, ["empty job-shop file: expected 'jobs machines' then one line per job"])
    lines, name = _one_of(where, lines, instance)
    try:
        n_jobs, n_machines, jobs = _parsed(where, lines)
    except ScenarioError:
        if _flexible(lines):
            raise ScenarioError(where, ["this is a flexible job shop (Brandimarte's .fjs layout: each operation "
                                        "lists the machines that may run it, each with its own duration); labtwin "
                                        f"reads classic job shops, one machine per operation ({FORMATS})"]) from None
        raise
    if not (1 <= n_jobs <= MAX_JOBS and 1 <= n_machines <= MAX_MACHINES):
        raise ScenarioError(where, [f"{n_jobs} jobs on {n_machines} machines; expected 1-{MAX_JOBS} jobs "
                                    f"on 1-{MAX_MACHINES} machines"])
    if len(jobs) != n_jobs:
        follow = counted(len(jobs), "job line follows", "job lines follow")
        raise ScenarioError(where, [f"the header says {n_jobs} jobs and {follow} it: one line per job"])
    empty = [j for j, job in enumerate(jobs) if not job]
    if empty:
        raise ScenarioError(where, [f"job {empty[0]} has no operations: each job line holds 'machine duration' pairs"])
    stray = [(j, m) for j, job in enumerate(jobs) for m, _ in job if not 0 <= m < n_machines]
    if stray:
        raise ScenarioError(where, [f"job {stray[0][0]}: machine {stray[0][1]} is outside 0..{n_machines - 1} (the "
                                    f"header says {n_machines} machines, numbered from 0)"])
    bad = [(j, d) for j, job in enumerate(jobs) for _, d in job if not 0 <= d <= MAX_DURATION]
    if bad:
        raise ScenarioError(where, [f"job {bad[0][0]}: duration {bad[0][1]} is outside 0..{MAX_DURATION:,}"])
    return Instance(name or path.stem, n_machines, jobs)


def _parsed(where: str, lines: list[tuple[int, str]]) -> tuple[int, int, list]:
    labels = [k for k, (_, ln) in enumerate(lines) if ln.lower().rstrip(":") in ("times", "machines")]
    return _taillard_labelled(where, lines, labels) if labels else _unlabelled(where, lines)


def _flexible(lines: list[tuple[int, str]]) -> bool:
    """Whether the lines are a flexible job shop: 'jobs machines mean-machines-per-operation', then per job its
    operation count and, per operation, how many machines may run it and that many 'machine duration' pairs."""
    head = lines[0][1].split() if lines else []
    if len(head) != 3 or _integers(" ".join(head[:2])) is None or len(lines) < 2:
        return False
    try:
        float(head[2])
    except ValueError:
        return False
    for _, text in lines[1:]:
        row = _integers(text)
        if not row or len(row) < 2:
            return False
        k, ops = 1, row[0]
        for _ in range(ops):
            if k >= len(row):
                return False
            k += 1 + 2 * row[k]
        if k != len(row):
            return False
    return True


def _integers(text: str) -> list[int] | None:
    try:
        return [int(x) for x in text.replace(",", " ").split()]
    except ValueError:
        return None


def _numbers(where: str, lines: list[tuple[int, str]]) -> list[list[int]]:
    rows = []
    for i, text in lines:
        row = _integers(text)
        if row is None:
            raise ScenarioError(where, [f"line {i}: {text[:60]!r} is not a row of whole numbers ({FORMATS})"])
        rows.append(row)
    return rows


def _unlabelled(where: str, lines: list[tuple[int, str]]) -> tuple[int, int, list]:
    """The standard format, or Taillard's matrices without their labels; lines of words before the header (an
    OR-Library instance's title and description) are skipped."""
    start = next((k for k, (_, ln) in enumerate(lines) if _integers(ln)), None)
    if start is None:
        raise ScenarioError(where, [f"no line of numbers: {FORMATS}"])
    head = _integers(lines[start][1]) or []
    if len(head) < 2:
        raise ScenarioError(where, [f"line {lines[start][0]}: expected 'jobs machines' ({FORMATS})"])
    n_jobs, n_machines = head[:2]
    rows = _numbers(where, lines[start + 1:])
    visits = _from_zero(rows[n_jobs:], n_machines) if len(rows) == 2 * n_jobs else None
    if visits is not None and all(len(r) == n_machines for r in rows[:n_jobs]):
        return n_jobs, n_machines, _jobs(rows[:n_jobs], visits)
    if len(rows) > n_jobs:
        raise ScenarioError(where, [f"line {lines[start + 1 + n_jobs][0]}: {len(rows)} rows after the header's "
                                    f"{n_jobs} jobs ({FORMATS}; one instance per file)"])
    jobs = []
    for (i, _), row in zip(lines[start + 1:], rows):
        if len(row) % 2:
            raise ScenarioError(where, [f"line {i}: an odd count of numbers ({len(row)}): expected 'machine "
                                        f"duration' pairs ({FORMATS})"])
        jobs.append(list(zip(row[0::2], row[1::2])))
    return n_jobs, n_machines, jobs


def _taillard_labelled(where: str, lines: list[tuple[int, str]], labels: list[int]) -> tuple[int, int, list]:
    """Taillard's own layout: a line of words, 'jobs machines seeds bounds', 'Times', the durations' matrix,
    'Machines', the machines' matrix (numbered from 1)."""
    names = [lines[k][1].lower().rstrip(":") for k in labels]
    if len(names) <= 2 and names != ["times", "machines"]:
        has = " then ".join(repr(lines[k][1]) for k in labels) + (" only" if len(labels) == 1 else "")
        raise ScenarioError(where, [f"line {lines[labels[0]][0]}: Taillard's layout has 'Times' and its durations, "
                                    f"then 'Machines' and the machines; this one has {has}"])
    if names != ["times", "machines"]:
        raise ScenarioError(where, [f"line {lines[labels[2 if len(labels) > 2 else 0]][0]}: found "
                                    f"{len(names)} 'Times'/'Machines' labels; a file holds one instance, or several "
                                    "each under its own 'Nb of jobs, Nb of Machines, ...' line, as Taillard's own "
                                    "files have them"])
    t, m = labels
    head = [row for _, row in ((i, _integers(ln)) for i, ln in lines[:t]) if row]
    if not head or len(head[-1]) < 2:
        raise ScenarioError(where, [f"line {lines[t][0]}: no 'jobs machines' line before 'Times' ({FORMATS})"])
    n_jobs, n_machines = head[-1][:2]
    times, machines = _numbers(where, lines[t + 1:m]), _numbers(where, lines[m + 1:])
    if len(times) != n_jobs or len(machines) != n_jobs or any(len(r) != n_machines for r in times + machines):
        raise ScenarioError(where, [f"expected {n_jobs} rows of {n_machines} numbers after 'Times' and after "
                                    f"'Machines'; found {len(times)} and {len(machines)} rows"])
    visits = _from_zero(machines, n_machines)
    if visits is None:
        raise ScenarioError(where, [f"line {lines[m][0]}: each row after 'Machines' must visit every machine "
                                    f"1..{n_machines} once"])
    return n_jobs, n_machines, _jobs(times, visits)


def _from_zero(machines: list[list[int]], n: int) -> list[list[int]] | None:
    """The machines' matrix numbered from 0, if each row visits every one of the ``n`` machines once, numbered
    from 1 (Taillard's) or from 0; else None."""
    first = 0 if any(0 in row for row in machines) else 1
    if not machines or any(sorted(row) != list(range(first, first + n)) for row in machines):
        return None
    return [[m - first for m in row] for row in machines]


def _jobs(times: list[list[int]], machines: list[list[int]]) -> list[list[tuple[int, int]]]:
    return [list(zip(ms, ts)) for ts, ms in zip(times, machines)]


def shop_path(base_dir: Path, file: str | Path) -> Path:
    """A job-shop file as a scenario or a command line names it: beside the scenario (``jobshop/la02.txt`` of
    ``scenarios/jobshop.yaml``), or else in the current directory (a shop of the user's own, named from where the
    command runs); one in neither is refused naming both places."""
    beside = base_dir / file
    if beside.exists() or Path(file).is_absolute():
        return beside
    here = Path(file)
    if here.exists():
        return here
    guess = nearest_file(beside) or nearest_file(here) or "check the path"
    raise ScenarioError(str(file), [f"file not found, neither beside the scenario ({beside}) nor in the current "
                                    f"directory ({Path.cwd() / file}): {guess}"])


def expand(scenario: Scenario, base_dir: Path, source: str = "") -> Scenario:
    """The lab and the fixed list of experiments (one per job) of the scenario's instance. A budget or a number in
    the lab the scenario (or the command line) gives is kept: the first ``budget`` jobs, ``max_in_flight`` of them
    at once; a planner other than ``fixed`` is refused (the jobs are the experiments)."""
    asked = scenario.campaign.model_fields_set
    if "planner" in asked and scenario.campaign.planner != "fixed":
        raise ScenarioError(source or scenario.name, [
            f"campaign.planner: {scenario.campaign.planner!r} cannot plan a job shop: its experiments are the jobs of "
            f"{scenario.jobshop.file}, in order (planner fixed); leave campaign.planner out"])
    lab = as_lab(scenario, read(shop_path(base_dir, scenario.jobshop.file), scenario.jobshop.instance), rename=False)
    kept: dict[str, Any] = {k: min(getattr(scenario.campaign, k), lab.campaign.budget)
                            for k in ("budget", "max_in_flight") if k in asked}
    if "budget" in kept:  # the shop is its first jobs: what a bound or a plan of it reads too
        proposals = lab.campaign.planner_options["proposals"][:kept["budget"]]
        kept["planner_options"] = {**lab.campaign.planner_options, "proposals": proposals}
    return lab.model_copy(update={"campaign": lab.campaign.model_copy(update=kept)}) if kept else lab


def run_name(lab: str, shop: str) -> str:
    """The name of a run of shop ``shop`` in lab ``lab`` (``jobshop_la02``), made a valid scenario name."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", f"{lab}_{shop}")
    return ("_" + name if name[0] in ".-" else name)[:63]


def generate(jobs: int, machines: int, low: int, high: int, rng: random.Random) -> Instance:
    """A random instance in the usual way (Taillard): each job visits every machine once, in a random
    order, for a duration drawn uniformly from [low, high]."""
    return Instance(f"random-{jobs}x{machines}", machines,
                    [[(m, rng.randint(low, high)) for m in rng.sample(range(machines), machines)] for _ in range(jobs)])


def as_lab(scenario: Scenario, inst: Instance, rename: bool = True) -> Scenario:
    """``scenario`` with ``inst``'s machines as its devices and its jobs as its experiments, named after ``inst``
    (``jobshop_random-20x15``; ``rename=False``: the scenario's own name, for the shop its file names)."""
    devices = {
        f"m{m}": {
            "driver": "machine",
            "steps": ["op"],
            "duration": {"mean_s": 0, "cv": 0, "plus_param": "duration_s"},
        }
        for m in range(inst.machines)
    }
    proposals = [
        {
            "params": {"job": j},
            "route": [
                {"step": "op", "device": f"m{m}", "params": {"duration_s": d}} for m, d in job
            ],
        }
        for j, job in enumerate(inst.jobs)
    ]
    data = scenario.model_dump()
    data["devices"] = devices
    if rename:
        data["name"] = run_name(scenario.lab, inst.name)
    data["campaign"].update(
        planner="fixed",
        budget=len(proposals),
        max_in_flight=len(proposals),
        stop_on_target=False,
        planner_options={"proposals": proposals},
    )
    return Scenario.model_validate(data)
