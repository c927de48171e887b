"""Whether this process tells a person how its long work goes (a plugin's progress lines on stderr, such as the rl
scheduler's planning): not in a bench's or a what-if's worker processes, whose hundreds of campaigns would bury the
command's own progress bar under theirs (the command says it once, when it checks the plugin)."""

from __future__ import annotations

_quiet = False


def quiet_progress() -> None:
    """From now on this process tells no progress (a worker's initialiser calls it)."""
    global _quiet
    _quiet = True


def tells_progress() -> bool:
    return not _quiet
