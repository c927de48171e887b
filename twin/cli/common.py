"""What every command group of ``twin`` shares: the apps, the consoles, and how an error is shown."""

from __future__ import annotations

import typer
from rich.console import Console

from twin.core.errors import TwinError

app = typer.Typer(help="labtwin: a digital twin of a self-driving lab.", no_args_is_help=True,
                  pretty_exceptions_enable=False, add_completion=False)
device_app = typer.Typer(help="Run one device actor in this process.", no_args_is_help=True)
app.add_typer(device_app, name="device")
bench_app = typer.Typer(help="Compare planners and schedulers over many seeds.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
scheduler_app = typer.Typer(help="Run a scheduler agent in this process.", no_args_is_help=True)
driver_app = typer.Typer(help="Write your own device drivers.", no_args_is_help=True)
app.add_typer(driver_app, name="driver")
app.add_typer(scheduler_app, name="scheduler")
security_app = typer.Typer(help="Certificates and access control for a lab's bus.", no_args_is_help=True)
app.add_typer(security_app, name="security")
console = Console()
err = Console(stderr=True, soft_wrap=True)


def _fail(exc: TwinError) -> None:
    err.print(f"[bold red]error:[/] {exc}", highlight=False)
    raise typer.Exit(2)
