"""The Rerun recorder: the only module that imports rerun.

A ``RerunCanvas`` draws what the ``LabObserver`` derives on one lab-time
timeline (``lab_time``) plus a sequence timeline of experiment numbers
(``experiment``); ``open_recording`` attaches the sinks a user asked for —
a file, a spawned viewer, a loopback web viewer — and never lets a sink that
fails take the campaign down.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from twin.observer import STATES

log = logging.getLogger(__name__)
LEVELS = {"DEBUG": rr.TextLogLevel.DEBUG, "INFO": rr.TextLogLevel.INFO, "WARN": rr.TextLogLevel.WARN,
          "ERROR": rr.TextLogLevel.ERROR}
STATE_COLOURS = {"offline": 0x606060FF, "idle": 0x4C78A8FF, "failed": 0xE45756FF, "quarantined": 0xF58518FF,
                 "busy": 0x54A24BFF}


def blueprint() -> rrb.Blueprint:
    """Devices, objective, spectra and log: the panels a campaign is watched in."""
    everything = rrb.VisibleTimeRange("lab_time", start=rrb.TimeRangeBoundary.infinite(),
                                      end=rrb.TimeRangeBoundary.cursor_relative())
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.StateTimelineView(origin="/devices", name="Devices"),
                rrb.TimeSeriesView(origin="/objective", name="Objective and best so far"),
            ),
            rrb.Horizontal(
                rrb.Spatial2DView(origin="/spectra", name="Spectra (latest, with targets)"),
                rrb.TimeSeriesView(origin="/queue", name="Queue"),
                rrb.Spatial3DView(origin="/planner", name="Proposals (normalised box)", time_ranges=[everything]),
            ),
            rrb.Horizontal(
                rrb.TextLogView(origin="/log", name="Decisions and faults"),
                rrb.TimeSeriesView(origin="/telemetry", name="Telemetry"),
                rrb.TimeSeriesView(origin="/utilisation", name="Utilisation"),
                rrb.TextDocumentView(origin="/summary", name="Summary"),
            ),
            row_shares=[2, 2, 2],
        ),
        collapse_panels=True,
    )


class RerunCanvas:
    """Draws on one recording stream; every call is stamped with lab time."""

    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rec = rec
        self._configured: set[str] = set()

    def _at(self, t: float, seq: int | None) -> None:
        self.rec.reset_time()
        self.rec.set_time("lab_time", duration=t)
        if seq is not None:
            self.rec.set_time("experiment", sequence=seq)

    def scalar(self, path: str, t: float, value: float, seq: int | None = None) -> None:
        self._at(t, seq)
        self.rec.log(path, rr.Scalars(value))

    def state(self, path: str, t: float, state: str) -> None:
        if path not in self._configured:
            self._configured.add(path)
            names = list(STATES)
            self.rec.log(path, rr.StateConfiguration(values=names, colors=[STATE_COLOURS[n] for n in names]),
                         static=True)
        self._at(t, None)
        self.rec.log(path, rr.StateChange(state=state))

    def text(self, path: str, t: float, text: str, level: str) -> None:
        self._at(t, None)
        self.rec.log(path, rr.TextLog(text, level=LEVELS.get(level, rr.TextLogLevel.INFO)))

    def line(self, path: str, t: float, points: list[tuple[float, float]], seq: int | None = None) -> None:
        self._at(t, seq)
        xy = np.asarray(points, dtype=np.float32)
        xy[:, 1] = 300.0 * (1.0 - xy[:, 1])  # screen y grows downwards; 300 px per unit of signal
        self.rec.log(path, rr.LineStrips2D([xy]))

    def points(self, path: str, t: float, points: list[tuple[float, ...]], seq: int | None = None) -> None:
        self._at(t, seq)
        pts = np.asarray(points, dtype=np.float32)
        if pts.shape[1] == 2:
            pts[:, 1] = 300.0 * (1.0 - pts[:, 1])
            self.rec.log(path, rr.Points2D(pts, radii=3.0))
        else:
            self.rec.log(path, rr.Points3D(pts, radii=0.01))

    def document(self, path: str, markdown: str) -> None:
        self.rec.log(path, rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=True)


@dataclass
class Recording:
    """A recording stream with its sinks; ``close`` flushes and stops them."""

    rec: rr.RecordingStream
    canvas: RerunCanvas
    messages: list[str] = field(default_factory=list)
    server: subprocess.Popen | None = None
    url: str = ""

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def stop_serving(self) -> None:
        if self.server is not None:
            self.server.terminate()
            self.server.wait(timeout=10)
            self.server = None


def open_recording(recording_id: str, save: str | Path | None = None, viewer: bool = False,
                   serve: bool = False, serve_port: int = 0, web_port: int = 0) -> Recording:
    """A recording with the sinks asked for; a sink that cannot start is reported, not fatal."""
    rec = rr.RecordingStream("labtwin", recording_id=recording_id)
    rec.set_log_time_enabled(False)  # only lab time: a replay then equals the live recording
    rec.set_log_tick_enabled(False)
    out = Recording(rec, RerunCanvas(rec))
    sinks: list[Any] = []
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(str(save)))
    if viewer:
        url = _spawn_viewer(out)
        if url:
            sinks.append(rr.GrpcSink(url))
    if serve:
        url = _serve(out, serve_port, web_port)
        if url:
            sinks.append(rr.GrpcSink(url))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=blueprint())
    return out


def _rerun_cli() -> str | None:
    here = Path(sys.executable).parent / "rerun"
    return str(here) if here.exists() else shutil.which("rerun")


def _free(port: int) -> int | None:
    """``port`` if it can be bound on loopback (0 picks one), else None."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return None
        return s.getsockname()[1]


def _spawn_viewer(out: Recording) -> str | None:
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        out.messages.append("viewer: no display here (DISPLAY is unset); the campaign runs without it. "
                            "Use --save run.rrd and open it with `rerun run.rrd`, or --serve for a web viewer.")
        return None
    cli = _rerun_cli()
    port = _free(0)
    if cli is None or port is None:
        out.messages.append("viewer: the rerun command is not installed; the campaign runs without it")
        return None
    subprocess.Popen([cli, "--port", str(port), "--bind", "127.0.0.1"], stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)
    return f"rerun+http://127.0.0.1:{port}/proxy"


def _serve(out: Recording, grpc_port: int, web_port: int) -> str | None:
    cli = _rerun_cli()
    grpc, web = _free(grpc_port), _free(web_port)
    if cli is None:
        out.messages.append("serve: the rerun command is not installed; the campaign runs without serving")
        return None
    if grpc is None or web is None:
        busy = grpc_port if grpc is None else web_port
        out.messages.append(f"serve: port {busy} on 127.0.0.1 is in use; pick another with --serve-port/--web-port. "
                            "The campaign runs without serving.")
        return None
    out.server = subprocess.Popen(
        [cli, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc), "--web-viewer-port", str(web)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    if not _wait_listening(grpc, out.server):
        err = out.server.stderr.read().decode(errors="replace")[-300:] if out.server.stderr else ""
        out.messages.append(f"serve: the rerun server did not start ({err.strip() or 'no reason given'}); "
                            "the campaign runs without serving")
        out.server = None
        return None
    grpc_url = f"rerun+http://127.0.0.1:{grpc}/proxy"
    out.url = f"http://127.0.0.1:{web}/?url={grpc_url}"
    out.messages.append(f"serving the live campaign at {out.url}")
    return grpc_url


def _wait_listening(port: int, proc: subprocess.Popen, seconds: float = 15.0) -> bool:
    # wall time on purpose: this waits for a server process to come up, outside the lab
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.05)
    return False
