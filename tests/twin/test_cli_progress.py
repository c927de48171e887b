"""Progress where no one watches a terminal: a long command piped to a log says how far it has got as it goes,
not only when it ends (rich's live bar prints nothing to a pipe until it stops)."""

import io
import os
import subprocess
import sys
from pathlib import Path

from rich.console import Console

from twin.cli.progress import PlainProgress, bar_progress

ROOT = Path(__file__).resolve().parents[2]


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_log_gets_a_line_at_the_start_every_interval_while_work_moves_and_at_the_end():
    out, clock = io.StringIO(), Clock()
    progress = PlainProgress(Console(file=out, width=200), ("lab {task.fields[lab]}", "{task.fields[status]}"),
                             every_s=10, clock=clock)
    with progress:
        task = progress.add_task("busy_lab [x]", total=40, lab="0 s", status="")
        for second in range(1, 60):
            clock.now = 100 + second
            progress.update(task, completed=second // 2, lab=f"{second} h")
        clock.now = 200
        progress.update(task, completed=40, status="[yellow]paused by ann (twin ctl resume)[/]")
    lines = out.getvalue().splitlines()
    assert lines[0] == "busy_lab [x]: 0/40  lab 0 s  0:00:00"  # markup in a name is shown as written
    assert lines[1:-1] == [f"busy_lab [x]: {s // 2}/40  lab {s} h  0:00:{s:02d}" for s in (10, 20, 30, 40, 50)]
    assert lines[-1] == "busy_lab [x]: 40/40  lab 59 h  paused by ann (twin ctl resume)  0:01:40"  # markup is styling


def test_lines_thin_out_as_a_long_run_goes_on_and_none_repeat_a_count():
    out, clock = io.StringIO(), Clock()
    progress = PlainProgress(Console(file=out, width=200), every_s=10, clock=clock)
    with progress:
        task = progress.add_task("night", total=3_600_000)
        for second in range(1, 36_001):
            clock.now = 100 + second
            progress.advance(task, 100)
            if second == 5_000:  # a stall: no line while nothing moves
                clock.now += 3_000
                progress.advance(task, 0)
    lines = out.getvalue().splitlines()
    assert 20 <= len(lines) <= 60
    counts = [line.split(": ")[1].split()[0] for line in lines]
    assert len(counts) == len(set(counts)) and counts[-1] == "3600000/3600000"


class Timers:
    """Timers that go off when the test says, at the test's clock."""

    def __init__(self) -> None:
        self.set: list[tuple[float, object]] = []

    def __call__(self, wait: float, then):
        timers = self

        class Timer:
            daemon = False
            cancelled = False

            def start(self) -> None:
                timers.set.append((wait, self))

            def cancel(self) -> None:
                self.cancelled = True

            def go_off(self) -> None:
                if not self.cancelled:
                    then()

        return Timer()


def test_a_move_with_no_update_after_it_is_said_when_it_is_due():
    out, clock, timers = io.StringIO(), Clock(), Timers()
    progress = PlainProgress(Console(file=out, width=200), every_s=10, clock=clock, timer=timers)
    with progress:
        task = progress.add_task("r30x20: 4 schedulers", total=4)
        clock.now = 101
        progress.advance(task)
        clock.now = 102
        progress.advance(task)  # two quick runs, then one that takes minutes
        assert out.getvalue().splitlines() == ["r30x20: 4 schedulers: 0/4  0:00:00"]
        assert [wait for wait, _ in timers.set] == [9]  # one timer, for when a line is due
        clock.now = 110
        timers.set[0][1].go_off()
        assert out.getvalue().splitlines()[-1] == "r30x20: 4 schedulers: 2/4  0:00:10"
        clock.now = 300
        progress.advance(task)
        clock.now = 301
        progress.advance(task)
        assert len(timers.set) == 2 and not timers.set[1][1].cancelled  # 4/4 not due yet: said by the timer or the end
    assert timers.set[1][1].cancelled  # the end said it, and the timer will not
    assert out.getvalue().splitlines()[-2:] == ["r30x20: 4 schedulers: 3/4  0:03:20", "r30x20: 4 schedulers: 4/4  0:03:21"]


def test_a_terminal_gets_the_live_bar_and_a_pipe_the_lines():
    assert isinstance(bar_progress(Console(file=io.StringIO())), PlainProgress)
    live = bar_progress(Console(file=io.StringIO(), force_terminal=True, force_interactive=True))
    assert not isinstance(live, PlainProgress)
    assert not isinstance(bar_progress(Console(file=io.StringIO()), disable=True), PlainProgress)


# a real pipe, to a command in a process of its own
def test_a_piped_campaign_reports_its_progress_on_stderr():
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE")}
    res = subprocess.run([sys.executable, "-m", "twin", "run", "scenarios/quantum_dots.yaml", "--bus", "memory"],
                         capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert res.returncode == 0, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.startswith("quantum_dots (virtual clock, memory bus): ")]
    assert lines[0].startswith("quantum_dots (virtual clock, memory bus): 0/120")
    done = int(lines[-1].split(": ")[1].split("/")[0])
    assert f"│ experiments │ {done} done," in " ".join(res.stdout.split()) and done > 0


def test_work_of_a_known_size_says_the_time_left_at_its_pace_and_a_campaign_does_not():
    out, clock = io.StringIO(), Clock()
    progress = PlainProgress(Console(file=out, width=200), every_s=10, clock=clock, remaining=True)
    with progress:
        task = progress.add_task("flaky_lab: 3 variants × 20 seeds", total=60)
        clock.now, done = 110, 15
        progress.update(task, completed=done)
        clock.now = 130
        progress.update(task, completed=60)
    lines = out.getvalue().splitlines()
    assert lines == ["flaky_lab: 3 variants × 20 seeds: 0/60  0:00:00",
                     # 45 more at 1.5 a second
                     "flaky_lab: 3 variants × 20 seeds: 15/60  0:00:10  about 0:00:30 left",
                     "flaky_lab: 3 variants × 20 seeds: 60/60  0:00:30"]
    live = bar_progress(Console(file=io.StringIO(), force_terminal=True, force_interactive=True))
    assert any(type(c).__name__ == "TimeRemainingColumn" for c in live.columns)
    campaign = bar_progress(Console(file=io.StringIO(), force_terminal=True, force_interactive=True), remaining=False)
    assert not any(type(c).__name__ == "TimeRemainingColumn" for c in campaign.columns)
    assert not bar_progress(Console(file=io.StringIO()), remaining=False).remaining



def test_labtwin_progress_s_sets_the_interval_off_a_terminal(monkeypatch):
    monkeypatch.setenv("LABTWIN_PROGRESS_S", "0.25")
    assert bar_progress(Console(file=io.StringIO()))._every_s == 0.25
    monkeypatch.delenv("LABTWIN_PROGRESS_S")
    assert bar_progress(Console(file=io.StringIO()))._every_s == 10
