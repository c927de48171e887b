"""The Rerun viewer and web server as child processes of the lab: started on loopback, each in its own session;
the server is stopped with its whole process group (SIGTERM of `twin run --serve` leaves no orphan), and ends
with the lab however the lab ends (SIGKILL too). The native viewer is left open for a person to go on looking."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path


def stop(proc: subprocess.Popen) -> None:
    """End a rerun process and its children (the `rerun` command is a wrapper that starts the viewer)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _rerun_cli() -> str | None:
    here = Path(sys.executable).parent / "rerun"
    return str(here) if here.exists() else shutil.which("rerun")


#: Started in place of Rerun's binary: made to end with the thread that started it, unless that has ended already,
#: then it becomes the binary.
_DIES_WITH_US = ("import os, sys\n"
                 "from twin.core.parent_death import ends_with_parent\n"
                 "if ends_with_parent(int(sys.argv[1])):\n"
                 "    os.execv(sys.argv[2], sys.argv[2:])\n")


def _serving_command() -> list[str] | None:
    """The command that starts Rerun's server so that it ends with this process, however that ends: the `rerun`
    script is a Python wrapper that starts the binary as a child of its own and forwards no signal, and a lab
    killed with SIGKILL left the binary serving, its ports held, for good. Where the binary cannot be found (or not
    on Linux), the `rerun` command, stopped with its process group as before."""
    binary = os.environ.get("RERUN_CLI_PATH")  # as the wrapper itself honours it
    if binary is None:
        spec = importlib.util.find_spec("rerun_cli")
        places = [Path(p) / "rerun" for p in (spec.submodule_search_locations or [])] if spec else []
        binary = next((str(p) for p in places if p.is_file()), None)
    if binary is not None and sys.platform.startswith("linux"):
        return [sys.executable, "-c", _DIES_WITH_US, str(os.getpid()), binary]
    cli = _rerun_cli()
    return [cli] if cli else None


def _free(port: int) -> int | None:
    """``port`` if it can be bound on loopback (0 picks one), else None."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return None
        return s.getsockname()[1]


def spawn_viewer(messages: list[str]) -> str | None:
    """A native viewer in its own session; its gRPC URL, or None (and why, in ``messages``)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        messages.append("viewer: no display here (DISPLAY is unset); the campaign runs without it. "
                        "Use --save run.rrd and open it with `rerun run.rrd`, or --serve for a web viewer.")
        return None
    cli = _rerun_cli()
    port = _free(0)
    if cli is None or port is None:
        messages.append("viewer: the rerun command is not installed; the campaign runs without it")
        return None
    subprocess.Popen([cli, "--port", str(port), "--bind", "127.0.0.1"], stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)
    return f"rerun+http://127.0.0.1:{port}/proxy"


def serve(grpc_port: int, web_port: int, messages: list[str]) -> tuple[subprocess.Popen, str, str] | None:
    """A loopback web viewer and gRPC server: (its process, the web URL, the gRPC URL), or None (and why, in
    ``messages``)."""
    cli = _serving_command()
    grpc, web = _free(grpc_port), _free(web_port)
    if cli is None:
        messages.append("serve: the rerun command is not installed; the campaign runs without serving")
        return None
    if grpc is None or web is None:
        busy = grpc_port if grpc is None else web_port
        messages.append(f"serve: port {busy} on 127.0.0.1 is in use; pick another with --serve-port/--web-port. "
                        "The campaign runs without serving.")
        return None
    server = subprocess.Popen(
        [*cli, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc), "--web-viewer-port", str(web)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    if not _wait_listening(server, grpc, web):
        stop(server)
        err = server.stderr.read().decode(errors="replace")[-300:] if server.stderr else ""
        messages.append(f"serve: the rerun server did not start ({err.strip() or 'no reason given'}); "
                        "the campaign runs without serving")
        return None
    grpc_url = f"rerun+http://127.0.0.1:{grpc}/proxy"
    url = f"http://127.0.0.1:{web}/?url={grpc_url}"
    messages.append(f"serving the live campaign at {url}")
    return server, url, grpc_url


def _wait_listening(proc: subprocess.Popen, grpc: int, web: int, seconds: float = 15.0) -> bool:
    """Read the server's log until it says both its gRPC and web ports listen."""
    fd = proc.stderr.fileno()  # raw reads: a buffered reader could hold lines select() cannot see
    waiting, log_text = {f"127.0.0.1:{grpc}".encode(), f"127.0.0.1:{web}".encode()}, b""
    while waiting and len(log_text) < 1 << 20:
        ready, _, _ = select.select([fd], [], [], seconds)
        chunk = os.read(fd, 65536) if ready else b""
        if not chunk:
            return False
        log_text += chunk
        waiting = {w for w in waiting if w not in log_text}
    threading.Thread(target=_drain, args=(fd,), daemon=True).start()  # keep its pipe from filling
    return not waiting


def _drain(fd: int) -> None:
    with contextlib.suppress(OSError):
        while os.read(fd, 65536):
            pass
