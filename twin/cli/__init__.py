"""``twin``: a thin command line over the Python API (``twin.run``, ``twin.resume``, ...).

Each command group is a module that registers its commands on the apps in ``common``.
"""

from twin.cli import commands, control, distributed, export, learning, routes, whatif  # noqa: F401  (they register their commands)
from twin.cli.common import app

__all__ = ["app"]
