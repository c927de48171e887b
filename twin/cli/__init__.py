"""``twin``: a thin command line over the Python API (``twin.run``, ``twin.resume``, ...).

Each command group is a module that registers its commands on the apps in ``common``.
"""

import inspect

import typer

from twin.cli import (benches, commands, control, distributed, export, learning, report, routes,  # noqa: F401 (they
                      sharing, whatif)  # register their commands)
from twin.cli.common import app

__all__ = ["app"]


def _summaries_on_one_line(group: typer.Typer) -> None:
    """A command list shows each command's and group's first paragraph whole, as one paragraph (click cuts a
    group's at 45 characters: "Operate a running campaign: status, pause, resume, abort,...")."""
    for info in group.registered_commands:
        text = info.help or (info.callback.__doc__ if info.callback else None)
        if info.short_help is None and text:
            info.short_help = _first_paragraph(text)
    for sub in group.registered_groups:
        if sub.typer_instance is not None:
            text = sub.help or sub.typer_instance.info.help
            if not isinstance(sub.short_help, str) and isinstance(text, str):
                sub.short_help = _first_paragraph(text)
            _summaries_on_one_line(sub.typer_instance)


def _first_paragraph(text: str) -> str:
    return " ".join(inspect.cleandoc(text).split("\n\n")[0].split())


_summaries_on_one_line(app)
