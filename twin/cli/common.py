"""What every command group of ``twin`` shares: the apps, the consoles, and how an error is shown."""

from __future__ import annotations

import contextlib
import re
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.segment import Segment

from twin.cli.printable import PrintableConsole
from twin.core.counts import counted
from twin.core import keys
from twin.core.errors import ScenarioError, TwinError
from twin.core.printable import inert
from twin.core.whole_files import FULL_BYTES, free_bytes

if TYPE_CHECKING:
    from rich.table import Table

def command_group(help: str, **settings: Any) -> typer.Typer:
    """Commands whose help and errors are click's plain text, wrapped to the terminal's width: rich's panels cut
    an option's help short at 80 columns ("e.g. devices.spectromete…")."""
    return typer.Typer(help=help, no_args_is_help=True, rich_markup_mode=None, **settings)


app = command_group("labtwin: a digital twin of a self-driving lab.", pretty_exceptions_enable=False,
                    add_completion=False)


def _say_version(asked: bool) -> None:
    if asked:
        from twin.runtime.run_record import versions

        known = versions()
        print(f"labtwin {known.pop('labtwin', '?')} ("
              + ", ".join(f"{name} {v}" for name, v in known.items()) + ")")
        raise typer.Exit()


@app.callback()
def _top(version: Annotated[bool, typer.Option("--version", callback=_say_version, is_eager=True,
                                               help="print labtwin's version and its libraries', and exit")]
         = False) -> None:
    """labtwin: a digital twin of a self-driving lab."""
    _printable_anywhere()
    if not {"--help", "-h"} & set(sys.argv[1:]):  # a command's help is shown whatever the settings (click has
        # taken the command's arguments from its context by now)
        _settings_checked()


def _settings_checked() -> None:
    """A mistyped LABTWIN_… is refused before anything runs, not when the first journal or bar is made."""
    from twin.campaign.journal import flush_every
    from twin.cli.progress import plain_every_s

    try:
        plain_every_s()
        flush_every()
    except TwinError as exc:
        _fail(exc)


def _printable_anywhere() -> None:
    """A terminal that cannot show every character (PYTHONIOENCODING=ascii, a Latin-1 console) shows '?' for
    the ones it cannot, where a summary's dash or a unit's 'µ' ended the command in a UnicodeEncodeError."""
    for stream in (sys.stdout, sys.stderr):
        encoding = (getattr(stream, "encoding", None) or "").lower().replace("-", "").replace("_", "")
        if not encoding.startswith("utf") and hasattr(stream, "reconfigure"):
            with contextlib.suppress(ValueError, OSError):
                stream.reconfigure(errors="replace")


device_app = command_group("Run one device actor in this process.")
lab_app = command_group("Serve a lab that several campaigns share.")
app.add_typer(device_app, name="device")
app.add_typer(lab_app, name="lab")
bench_app = command_group("Compare planners and schedulers over many seeds.")
app.add_typer(bench_app, name="bench")
scheduler_app = command_group("Run a scheduler agent in this process.")
driver_app = command_group("Write your own device drivers.")
app.add_typer(driver_app, name="driver")
app.add_typer(scheduler_app, name="scheduler")
security_app = command_group("Certificates and access control for a lab's bus.")
app.add_typer(security_app, name="security")
# emoji off: a name like "raising:Boom:" is not an emoji code; markup off: a path, a SMILES ("c1cc[nH]c1") or an
# error quoting either prints as it is, never read as rich's [tags] (the few styled lines ask for markup=True)
# and control characters in text from elsewhere (a driver's error, an operator's reason) shown as escapes
console = PrintableConsole(emoji=False, markup=False)
err = PrintableConsole(stderr=True, soft_wrap=True, emoji=False, markup=False)


def writable(option: str, *paths: Path | None) -> None:
    """Refuse, before any work, a file to write that cannot be: the runs, the training or the campaign would be
    lost at their end (its directory is made, as a recording's is; a file made to try is removed)."""
    for path in paths:
        if path is None:
            continue
        existed = path.exists()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a"):
                pass
        except OSError as exc:
            why = (f"its directory {path.parent} cannot be made: {exc.strerror}"
                   if exc.filename and str(exc.filename) != str(path) else exc.strerror or str(exc))
            _fail(TwinError(f"{option} {path}: cannot write it ({why}); give a file in a directory you can write "
                            "(nothing has run)"))
        if not existed:
            path.unlink()
        free = free_bytes(path)
        if free < FULL_BYTES:  # a file sink opened on a full disk hangs Rerun; any other file would be cut short
            _fail(TwinError(f"{option} {path}: its disk is full ({free:,} bytes free); free some space, or give a file "
                            "on another disk (nothing has run)"))


def recording_file(option: str, path: Path | None, or_picture: bool = False) -> None:
    """Refuse, before any work, a Rerun recording to a file that cannot be written or is not named ``.rrd`` (or,
    ``or_picture``, ``.png``): ``--save run.png`` wrote a recording that any tool would take for a broken picture."""
    writable(option, path)
    if path is None or path.suffix.lower() in ((".rrd", ".png") if or_picture else (".rrd",)):
        return
    rrd, png = path.with_suffix(".rrd"), path.with_suffix(".png")
    _fail(TwinError(f"{option} {path}: " + (f"give a Rerun recording, {rrd}, or a picture, {png}" if or_picture else
                                             f"this writes a Rerun recording, so name it {rrd}") + " (nothing has run)"))


def _fail(exc: TwinError) -> None:
    err.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, markup=True)
    raise typer.Exit(2)


def check_lab_name(value: str | None) -> str | None:
    """Every ``--lab``: a name a scenario's ``lab`` could have. A '/' or a wildcard would make the lab's keys
    another lab's, or every lab's."""
    if value is not None and not re.fullmatch(keys.LAB_NAME, value):
        raise typer.BadParameter(f"{value[:80]!r} is not a lab's name: a scenario's `lab` is letters, digits, '_' "
                                 "or '-', at most 64 (twin validate FILE shows it)")
    return value


def assignments(items: list[str]) -> dict:
    """``--set`` options, ``["a.b=1", "c=x"]`` → ``{"a.b": 1, "c": "x"}`` (values read as YAML)."""
    from twin.scenario.files import yaml_value

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            _fail(TwinError(f"--set {item!r}: expected FIELD=VALUE, e.g. devices.reactor.instances=1"))
        try:
            out[key.strip()] = yaml_value(value)
        except ScenarioError as exc:
            shown = item if len(item) <= 80 else item[:77] + "…"
            _fail(TwinError(f"--set {shown!r}: {exc.problems[0]}"))
    return out


def refuse_disagreeing(sets: dict, options: dict[str, tuple[str, Any]]) -> None:
    """A command's own option and a --set of the same field that say different things (``options``: field ->
    (option, its value or None when not given)) are refused, naming both: the option won without a word."""
    def shown(value: Any, joiner: str) -> str:
        if isinstance(value, list):
            return joiner.join(map(str, value))
        return f"{value:g}" if isinstance(value, float) else str(value)

    from twin.scenario.loading import disagreeing

    for field in disagreeing({field: value for field, (_, value) in options.items()}, sets)[:1]:
        (option, value), said = options[field], sets[field]
        said_text = f"[{shown(said, ', ')}]" if isinstance(said, list) else shown(said, "")
        _fail(TwinError(f"{option} {shown(value, ' ')} and --set {field}={said_text} disagree: give one of them"))


def say_if_still_written(journal: Path, what: str) -> None:
    """Under an export or a replay of a journal (or a lab's directory of them) a run is still writing: what was
    made holds what the run had written by then, which nothing else would tell."""
    from twin.campaign.journal_lock import writer

    for path in sorted(journal.glob("*.db")) if journal.is_dir() else [journal]:
        holder = writer(path)
        if holder is not None:
            err.print(f"{path}: a run{f' (process {holder})' if holder else ''} is still writing it, so {what} holds "
                      "what it had written by now; make it again when the run has ended", highlight=False)


def speed_heeded(speed: float | None, mode: str) -> None:
    """--speed paces a scaled clock; given for another (a virtual one runs as fast as it can, a wall one at 1), it
    would be ignored without a word, so it is refused."""
    if speed is not None and mode != "scaled":
        raise TwinError(f"--speed {speed:g} paces a scaled clock, and this lab's clock is {mode}: add --clock scaled "
                        f"to run it at {speed:g} lab-seconds per second, or leave --speed out")


def paired_assignments(items: list[str], compared: tuple[str, str] | None = None) -> dict:
    """``--set`` options of a bench or a what-if, which choose the runs' seeds themselves; ``compared``: the field
    a bench runs each of an option's values in, and that option (a --set of it would be replaced in every run)."""
    from twin.tools.planner_bench import SEEDS_PAIRED

    out = assignments(items)
    if "campaign.seed" in out:
        _fail(TwinError(f"--set campaign.seed: {SEEDS_PAIRED}"))
    if compared is not None and compared[0] in out:
        field, option = compared
        _fail(TwinError(f"--set {field}: this bench runs each of {option} in its place, so it would be replaced in "
                        f"every run; name it in {option} instead"))
    return out


def bar_progress(transient: bool = False, **options: Any) -> Any:
    """The progress every long command shows on stderr (a bar on a terminal, lines in a log); ``options``:
    ``fields`` and ``disable`` of ``twin.cli.progress.bar_progress``."""
    from twin.cli import progress

    return progress.bar_progress(err, transient, **options)


def narrow_table(header: list[str], title: str = "", caption: str = "") -> Table:
    """A table that reads at 80 columns: light rules, no padding at the edges, and cells (headers too) that
    wrap rather than end in '…'."""
    from rich import box
    from rich.table import Table

    table = Table(title=title or None, title_justify="left", caption=caption or None, caption_justify="left",
                  box=box.SIMPLE_HEAD, collapse_padding=True, pad_edge=False, show_edge=False)
    for h in header:
        table.add_column(h, overflow="fold")
    return table


_NUMBER = re.compile(r"\[?[≥≤~]?[-+−]?[\d.,]*\d(?:[%×]|[/–][-+−]?[\d.,]*\d%?)?\]?")


def print_table(table: Table) -> None:
    """Print a ``narrow_table`` with every column at least as wide as the longest number in it, so that a number
    is never split across lines (where "0.33" folded reads as "0.3"); names and words wrap instead. Words are
    kept whole too when the table still fits: the cells' and the headers' ("synthesiser", not "synthes" over
    "iser"), else broken after a hyphen, underscore or slash between letters ("least-" over "loaded"), the
    headers' first."""
    numbers_only = []
    for column in table.columns:
        cells = [cell for cell in column.cells if isinstance(cell, str)]
        numbers = [len(word) for cell in cells for word in cell.split() if _NUMBER.fullmatch(word)]
        numbers_only.append(max([column.min_width or 0, *numbers]))
        if cells and all(_NUMBER.fullmatch(c) or c in ("—", "-", "") for c in cells):
            # a column of numbers needs no more room than its widest one and its header's longest word: the rest
            # goes to the names
            column.max_width = max([*map(len, cells), *(len(w) for w in str(column.header).split())])
    headers = [str(column.header) for column in table.columns]
    contents: list[list[Any]] = [list(column._cells) for column in table.columns]  # rich keeps them in _cells
    broken = [_broken(h) for h in headers]
    stages = [(headers, contents, True), (broken, contents, True),
              (broken, [[_broken(c) for c in col] for col in contents], True),
              (headers, contents, False), (broken, contents, False)]
    for names, texts, whole in stages:
        for column, name, text, least in zip(table.columns, names, texts, numbers_only):
            column.header, column._cells = name, list(text)
            words = [len(w) for c in text if isinstance(c, str) for w in c.split()] if whole else []
            column.min_width = max(least, *words, *(len(w) for w in name.split()))
        width = fitted_width(table)
        if width is not None:
            break
    else:  # whole words leave no room: let them fold, as the numbers may not
        for column, name, text, least in zip(table.columns, headers, contents, numbers_only):
            column.header, column._cells, column.min_width = name, text, least
        width = fitted_width(table) or console.width
    # the title and caption at the terminal's width: rich wraps them at the table's, mid-phrase when it is narrow
    # ("1" over "of 11 shapes" above a table of one shape's rows)
    title, caption, table.title, table.caption = table.title, table.caption, None, None
    if title:
        console.print(title, highlight=False)
    console.print(table, width=width)
    if caption:
        console.print(caption, highlight=False)


def _broken(text: Any) -> Any:
    """``text`` with a line break after each hyphen, underscore or slash between two letters."""
    return _WORD_BREAK.sub("\n", text) if isinstance(text, str) else text


_WORD_BREAK = re.compile(r"(?<=[^\W\d_][-_/])(?=[^\W\d_])")


def fitted_width(table: Table) -> int | None:
    """The width to render ``table`` at so that it fits the terminal, or None if it cannot. Rich narrows the
    widest columns to fit and only then widens each to its min_width, so the table can come out wider than the
    terminal (and its caption cropped): ask it for less until it fits."""
    width = console.width
    for _ in range(16):  # each try narrows the table by about what it was over, not exactly
        lines = Segment.split_lines(console.render(table, console.options.update_width(width)))  # uncropped
        over = max((Segment.get_line_length(line) for line in lines), default=0) - console.width
        if over <= 0:
            return width
        width -= over
        if width < 20:
            return None
    return None


def say_ended_early(runs: list[tuple[str, str]]) -> None:
    """Under a bench's or a what-if's table: for each row whose runs ended early (``(label, why)`` per run, ``why``
    empty for a run that did not), how many did and the first reason, so that a row of noughts is not a mystery."""
    counts: dict[str, list[str]] = {}
    for label, why in runs:
        counts.setdefault(label, []).append(why)
    for label, whys in counts.items():
        early = [w for w in whys if w]
        if early:
            err.print(f"{label}: {len(early)} of {counted(len(whys), 'run', 'runs')} ended early — {early[0]}",
                      highlight=False, markup=False)


def machine_output(as_json: bool, csv_path: Path | None, header: list[str], rows: list[list[str]],
                   runs: list[dict], **extra) -> bool:
    """``--csv FILE``: one line per run (the raw numbers); ``--json``: the table's rows and every run, printed
    instead of the table. True when the table should not be printed."""
    import csv
    import json

    if csv_path is not None:
        fields = list(runs[0]) if runs else []
        with open(csv_path, "w", newline="") as f:
            w = csv.DictWriter(f, fields)
            w.writeheader()
            w.writerows({k: inert(v) for k, v in run.items()} for run in runs)
        err.print(f"wrote {csv_path} ({len(runs)} runs)", highlight=False)
    if as_json:
        console.print_json(json.dumps({**extra, "columns": header, "rows": [dict(zip(header, r)) for r in rows],
                                       "runs": runs}, default=str))
    return as_json


def keep_serving(recording, stopped: str) -> None:
    """--serve: the recording stays up until Ctrl-C or SIGTERM, so it can be looked at after the run; a campaign
    stopped by SIGTERM does not wait. Either way the Rerun server (its own process group) stops with us."""
    if recording.server is None:
        return
    if "SIGTERM" in stopped:
        recording.stop_serving()
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:  # said inside: a Ctrl-C or SIGTERM the moment it is read must still stop the server and exit cleanly
        err.print(f"the finished campaign is served at {recording.url} — Ctrl-C to stop", highlight=False)
        while recording.server.poll() is None:  # not wait(): a SIGINT the kernel hands another thread (Zenoh's,
            time.sleep(0.2)                     # Rerun's) only sets a flag, which a blocked waitpid never reads
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        recording.stop_serving()


def _interrupt(*_) -> None:
    raise KeyboardInterrupt
