"""``twin``: a thin command line over the Python API (``twin.run``, ``twin.resume``, ...).

Each command group is a module that registers its commands on the apps in ``common``.
"""

import inspect

import typer

from twin.cli import commands, control, distributed, export, learning, report, routes, whatif  # noqa: F401  (they register their commands)
from twin.cli.common import app

__all__ = ["app"]


def _summaries_on_one_line(group: typer.Typer) -> None:
    """A command list shows each command's first paragraph as one paragraph: typer's rich mode kept the
    docstring's line breaks there, so `twin --help` read "as tables (one file" / "each) and its provenance"."""
    for info in group.registered_commands:
        text = info.help or (info.callback.__doc__ if info.callback else None)
        if info.short_help is None and text:
            info.short_help = " ".join(inspect.cleandoc(text).split("\n\n")[0].split())
    for sub in group.registered_groups:
        if sub.typer_instance is not None:
            _summaries_on_one_line(sub.typer_instance)


_summaries_on_one_line(app)
