"""The Rerun recorder: the only module that imports rerun.

A ``RerunCanvas`` draws what the ``LabObserver`` derives on one lab-time
timeline (``lab_time``) plus a sequence timeline of experiment numbers
(``experiment``); ``open_recording`` attaches the sinks a user asked for —
a file, a spawned viewer, a loopback web viewer (their processes:
``viewer_process``) — and never lets a sink that fails take the campaign down.
"""

from __future__ import annotations

import itertools
import logging
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Callable

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from twin.core.errors import TwinError
from twin.core.whole_files import FULL_BYTES, free_bytes, locked
from twin.view import viewer_process
from twin.view.observer import STATES

log = logging.getLogger(__name__)
STATE_COLOURS = {"offline": 0x606060FF, "idle": 0x4C78A8FF, "failed": 0xE45756FF, "quarantined": 0xF58518FF,
                 "busy": 0x54A24BFF}


def _whole_time() -> rrb.TimeAxis:
    return rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                 end=rrb.TimeRangeBoundary.infinite()))


def series(origin: str, name: str, contents: Any = "$origin/**") -> rrb.TimeSeriesView:
    """A time-series panel over the whole of lab time."""
    return rrb.TimeSeriesView(origin=origin, contents=contents, name=name, axis_x=_whole_time())


def blueprint() -> rrb.Blueprint:
    """Devices, objective, spectra and log: the panels a campaign is watched in."""
    up_to_cursor = [rrb.VisibleTimeRange("lab_time", start=rrb.TimeRangeBoundary.infinite(),
                                         end=rrb.TimeRangeBoundary.cursor_relative())]
    whole = _whole_time()
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.StateTimelineView(origin="/devices", name="Devices", time_view=whole),
                series("/objective", "Objective (0 = target met) and best so far",
                       ["$origin/score", "$origin/best", "$origin/targets/**"]),
            ),
            rrb.Horizontal(
                rrb.Tabs(rrb.Spatial2DView(origin="/spectra", name="Spectra (latest, with targets)"),
                         rrb.Spatial2DView(origin="/route/plan", name="Route"),
                         rrb.TextDocumentView(origin="/route/steps", name="Route steps")),
                series("/queue", "Queue"),
                series("/objective/outputs", "Measured outputs"),
                rrb.Spatial3DView(origin="/planner", name="Proposals (normalised box)", time_ranges=up_to_cursor),
            ),
            rrb.Horizontal(
                rrb.TextLogView(origin="/log", name="Decisions and faults"),
                series("/telemetry", "Telemetry"),
                rrb.Tabs(series("/utilisation", "Utilisation"), series("/consumables", "Consumables")),
                rrb.TextDocumentView(origin="/summary", name="Summary"),
            ),
        ),
        rrb.TimePanel(timeline="lab_time", state="collapsed"),
        collapse_panels=True,
    )


def lab_blueprint(campaigns: list[str]) -> rrb.Blueprint:
    """A lab of several campaigns: its devices and their use at the top, a tab per campaign below."""
    whole = _whole_time()

    def campaign(c: str) -> rrb.Container:
        at = f"/campaigns/{c}"
        return rrb.Vertical(
            rrb.Horizontal(series(f"{at}/objective", "Objective (0 = target met) and best so far",
                                  ["$origin/score", "$origin/best", "$origin/targets/**"]),
                           series(f"{at}/queue", "Queue"),
                           rrb.StateTimelineView(origin=f"{at}/devices", name=f"Devices running {c}'s steps",
                                                 time_view=whole)),
            rrb.Horizontal(rrb.TextLogView(origin=f"{at}/log", name="Decisions and faults"),
                           rrb.Spatial2DView(origin=f"{at}/spectra", name="Spectra (latest, with targets)"),
                           rrb.TextDocumentView(origin=f"{at}/summary", name="Summary")),
            name=c)

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.StateTimelineView(origin="/devices", name="Devices (every campaign)", time_view=whole),
                           rrb.Tabs(series("/utilisation", "Utilisation"), series("/consumables", "Consumables"),
                                    series("/telemetry", "Telemetry"))),
            rrb.Tabs(*[campaign(c) for c in campaigns]),
        ),
        rrb.TimePanel(timeline="lab_time", state="collapsed"),
        collapse_panels=True,
    )


class _Series:
    """The rows of one entity waiting to be sent: lab times, experiment numbers (or none) and values."""

    __slots__ = ("kind", "path", "t", "seq", "values")

    def __init__(self, kind: str, path: str, with_seq: bool) -> None:
        self.kind, self.path = kind, path
        self.t: list[float] = []
        self.seq: list[int] | None = [] if with_seq else None
        self.values: list[Any] = []


class RerunCanvas:
    """Draws on one recording stream, in columns: rows are buffered per entity and sent with
    ``send_columns`` when ``flush`` is called or an entity has ``SERIES_ROWS`` waiting (one ``log``
    call per row cost more than the whole campaign; each ``send_columns`` costs ~0.3 ms however
    few rows it carries). Values are kept as given and become arrays only when sent, all rows at once.
    An entity is always drawn as one kind, with or without experiment numbers."""

    SERIES_ROWS = 4096

    def __init__(self, rec: rr.RecordingStream) -> None:
        self.rec = rec
        self._series: dict[str, _Series] = {}
        self.unsent = 0  # rows that could not be drawn (a device's odd values): dropped, and logged once

    def _add(self, kind: str, path: str, t: float, seq: int | None, value: Any) -> None:
        series = self._series.get(path)
        if series is None:
            series = self._open(kind, path, seq is not None)
        series.t.append(t)
        if seq is not None:
            series.seq.append(seq)  # an entity with experiment numbers has them all
        series.values.append(value)
        if len(series.t) >= self.SERIES_ROWS:
            self._send(series)

    def _open(self, kind: str, path: str, with_seq: bool) -> _Series:
        if kind == "state":
            names = list(STATES)
            self.rec.log(path, rr.StateConfiguration(values=names, colors=[STATE_COLOURS[n] for n in names]),
                         static=True)
        series = self._series[path] = _Series(kind, path, with_seq)
        return series

    def scalar(self, path: str, t: float, value: float, seq: int | None = None) -> None:
        self._add("scalar", path, t, seq, value)

    def scalars(self, path: str, t: float, values: tuple[float, ...], names: tuple[str, ...]) -> None:
        if path not in self._series:
            self.rec.log(path, rr.SeriesLines(names=list(names)), static=True)
        self._add("scalars", path, t, None, values)

    def state(self, path: str, t: float, state: str) -> None:
        self._add("state", path, t, None, state)

    def text(self, path: str, t: float, text: str, level: str) -> None:
        self._add("text", path, t, None, (text, level))

    def line(self, path: str, t: float, points: Any, seq: int | None = None) -> None:
        self._add("line", path, t, seq, points)

    def curve(self, path: str, t: float, x0: float, dx: float, y: list, seq: int | None = None) -> None:
        self._add("curve", path, t, seq, (x0, dx, y))

    def points(self, path: str, t: float, points: list[tuple[float, ...]], seq: int | None = None) -> None:
        self._add("points", path, t, seq, points[0])

    def document(self, path: str, markdown: str, t: float | None = None) -> None:
        if t is not None:
            self.rec.set_time("lab_time", duration=t)
        self.rec.log(path, rr.TextDocument(markdown, media_type=rr.MediaType.MARKDOWN), static=t is None)

    def image(self, path: str, t: float, png: bytes) -> None:
        self.rec.set_time("lab_time", duration=t)
        self.rec.log(path, rr.EncodedImage(contents=png, media_type="image/png"))

    def flush(self) -> None:
        for series in self._series.values():
            if series.t:
                self._send(series)

    def _send(self, series: _Series) -> None:
        t, seq, values = series.t, series.seq, series.values
        series.t, series.values = [], []
        if seq is not None:
            series.seq = []
        try:
            columns, keep = _columns(series.kind, values)
        except (ValueError, TypeError, OverflowError) as exc:  # a value no rule above foresaw: this batch only
            columns, keep = None, np.zeros(len(t), dtype=bool)
            log.warning("viewer: %d rows of %s could not be drawn (%r); the campaign goes on", len(t), series.path,
                        exc)
        if keep is not None:
            if not self.unsent:
                log.warning("viewer: a value on %s is not a number and is not drawn (more are counted, not logged); "
                            "the campaign goes on", series.path)
            self.unsent += int(len(keep) - keep.sum())
            if not keep.any():
                return
        # nanosecond arrays take rerun's vectorised path (a list of floats is converted one by one)
        times = np.round(np.asarray(t) * 1e9).astype("timedelta64[ns]")
        indexes = [rr.TimeColumn("lab_time", duration=times if keep is None else times[keep])]
        if seq is not None:
            numbers = np.asarray(seq, dtype=np.int64)
            indexes.append(rr.TimeColumn("experiment", sequence=numbers if keep is None else numbers[keep]))
        self.rec.send_columns(series.path, indexes=indexes, columns=columns)


def _columns(kind: str, values: list) -> tuple[Any, np.ndarray | None]:
    """The columns of these rows, and which rows they hold (None: all of them)."""
    # strings and points go over as arrow arrays: rerun's own conversion walks them one by one in Python
    if kind == "scalar":
        return rr.Scalars.columns(scalars=values), None
    if kind == "scalars":  # one row of several series each
        return rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64).ravel()).partition(
            [len(v) for v in values]), None
    if kind == "state":
        return rr.StateChange.columns(state=pa.array(values, pa.utf8())), None
    if kind == "text":
        return rr.TextLog.columns(text=pa.array([v[0] for v in values], pa.utf8()),
                                  level=pa.array([v[1] for v in values], pa.utf8())), None
    if kind == "points":
        pts = np.asarray(values, dtype=np.float32)
        if pts.shape[1] == 2:
            pts[:, 1] = 300.0 * (1.0 - pts[:, 1])  # screen y grows downwards; 300 px per unit of signal
            return rr.Points2D.columns(positions=pts, radii=np.full(len(pts), 3.0, np.float32)), None
        return rr.Points3D.columns(positions=pts, radii=np.full(len(pts), 0.01, np.float32)), None
    if kind == "curve":
        strips, keep = _curves(values)
        return rr.LineStrips2D.columns(strips=strips), keep
    strips, keep = _lines(values)
    return rr.LineStrips2D.columns(strips=strips), keep


def _curves(curves: list[tuple[float, float, list]]) -> tuple[pa.Array, np.ndarray | None]:
    """Polylines over evenly spaced x, ``(x0, dx, y)`` each, as one arrow list array: all points converted at
    once; a curve whose y are not numbers is left out (and only then is each converted on its own)."""
    lengths = np.fromiter((len(c[2]) for c in curves), dtype=np.int64, count=len(curves))
    total, keep = int(lengths.sum()), None
    try:
        y = np.fromiter(itertools.chain.from_iterable(c[2] for c in curves), dtype=np.float64, count=total)
    except (ValueError, TypeError):
        ys = [_numbers(c[2]) for c in curves]
        keep = np.fromiter((v is not None for v in ys), dtype=bool, count=len(ys))
        curves = [c for c, k in zip(curves, keep) if k]
        lengths = lengths[keep]
        y = np.concatenate([v for v in ys if v is not None]) if curves else np.zeros(0)
    starts: np.ndarray = np.zeros(len(lengths) + 1, dtype=np.int64)
    np.cumsum(lengths, out=starts[1:])
    x0 = np.fromiter((c[0] for c in curves), dtype=np.float64, count=len(curves))
    dx = np.fromiter((c[1] for c in curves), dtype=np.float64, count=len(curves))
    i = np.arange(len(y)) - np.repeat(starts[:-1], lengths)  # each point's place in its curve
    xy: np.ndarray = np.empty((len(y), 2), dtype=np.float32)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge value is drawn at infinity
        xy[:, 0] = np.repeat(x0, lengths) + np.repeat(dx, lengths) * i
        xy[:, 1] = 300.0 * (1.0 - y)
    return _strips(starts, xy), keep


def _numbers(y: list) -> np.ndarray | None:
    try:
        return np.fromiter(y, dtype=np.float64, count=len(y))
    except (ValueError, TypeError):
        return None


def _lines(lines: list) -> tuple[pa.Array, None]:
    """Polylines, each a list of (x, y) or an (N, 2) array."""
    xys = [np.asarray(p, dtype=np.float32).reshape(-1, 2) for p in lines]
    starts: np.ndarray = np.zeros(len(xys) + 1, dtype=np.int64)
    np.cumsum([len(p) for p in xys], out=starts[1:])
    xy = np.concatenate(xys)
    xy[:, 1] = 300.0 * (1.0 - xy[:, 1])
    return _strips(starts, xy), None


def _strips(starts: np.ndarray, xy: np.ndarray) -> pa.Array:
    """Polylines as one arrow list array: ``xy`` all their float32 (x, y) rows, polyline i from starts[i]."""
    flat = pa.array(xy.reshape(-1), pa.float32())
    strip_type = rr.components.LineStrip2DBatch._ARROW_DATATYPE
    return pa.ListArray.from_arrays(pa.array(starts.astype(np.int32)), pa.FixedSizeListArray.from_arrays(
        flat, type=strip_type.value_type), type=strip_type)


@dataclass
class Recording:
    """A recording stream with its sinks; ``close`` flushes and stops them."""

    rec: rr.RecordingStream
    canvas: RerunCanvas
    messages: list[str] = field(default_factory=list)
    server: subprocess.Popen | None = None
    url: str = ""
    before_close: list[Callable[[], None]] = field(default_factory=list)  # what draws its last rows first
    save: str = ""  # the file it is saved to, if any
    held: IO[bytes] | None = None  # that file, locked while this process writes it

    def close(self) -> None:
        try:
            self._close()
        finally:
            if self.held is not None:
                self.held.close()
                self.held = None

    def _close(self) -> None:
        for draw in self.before_close:
            draw()
        self.canvas.flush()
        again = "free some space, or --save it on another disk; `twin replay` rebuilds it from the run's journal"
        try:
            self.rec.flush()
        except RuntimeError as exc:  # Rerun's file writer stopped (a full disk, most likely); disconnect would hang
            raise TwinError(f"the recording {self.save} could not be written ({exc}): is its disk full? {again}") \
                from None
        self.rec.disconnect()
        if self.save:  # Rerun only logs a write that failed at the end: a full disk is the sign of one
            free = free_bytes(Path(self.save))
            if free < FULL_BYTES:
                raise TwinError(f"the disk of the recording {self.save} is full ({free:,} bytes free), so its end may "
                                f"be cut short: {again}")

    def lay_out(self, campaigns: list[str]) -> None:
        """The layout of a lab these campaigns share (sent again as campaigns come)."""
        self.rec.send_blueprint(lab_blueprint(campaigns))

    def stop_serving(self) -> None:
        if self.server is not None:
            viewer_process.stop(self.server)
            self.server = None


def log_curve(out: Recording, steps: int, values: dict[str, float], prefix: str = "training") -> None:
    """One evaluation of a training run, on its own ``training_steps`` timeline."""
    out.rec.set_time("training_steps", sequence=steps)
    for name, value in values.items():
        out.rec.log(f"{prefix}/{name}", rr.Scalars(float(value)))


def open_recording(recording_id: str, save: str | Path | None = None, viewer: bool = False,
                   serve: bool = False, serve_port: int = 0, web_port: int = 0,
                   campaign_layout: bool = True, campaigns: list[str] | None = None) -> Recording:
    """A recording with the sinks asked for; a sink that cannot start is reported, not fatal. ``campaigns``: the
    recording is of a lab these campaigns share (its layout has a tab for each)."""
    rec = rr.RecordingStream("labtwin", recording_id=recording_id)
    rec.set_log_time_enabled(False)  # only lab time: a replay then equals the live recording
    rec.set_log_tick_enabled(False)
    sinks: list[Any] = []
    held = None
    if save:
        Path(save).parent.mkdir(parents=True, exist_ok=True)
        # two runs given one --save wrote into one file at once, and both said it was saved
        held = locked(Path(save), f"{save} is being recorded by another run: wait for that run to end, or --save "
                                  "another file (nothing has run yet)")
    out = Recording(rec, RerunCanvas(rec), save=str(save or ""), held=held)
    if save:
        sinks.append(rr.FileSink(str(save)))
    if viewer:
        url = viewer_process.spawn_viewer(out.messages)
        if url:
            sinks.append(rr.GrpcSink(url))
    if serve:
        served = viewer_process.serve(serve_port, web_port, out.messages)
        if served:
            out.server, out.url, url = served
            sinks.append(rr.GrpcSink(url))
    if sinks:
        layout = lab_blueprint(campaigns) if campaigns is not None else blueprint() if campaign_layout else None
        rec.set_sinks(*sinks, default_blueprint=layout)
    return out


def save_whatif(path: str | Path, scenario: str, summary: list[dict[str, Any]]) -> None:
    """`twin whatif --save`: lab-hours against cost per variant (a labelled point each; up is more lab-hours),
    lab-hours, cost and each device type's utilisation as bar charts over the variants (in table order), and
    the variants' table."""
    rec = rr.RecordingStream("labtwin", recording_id=f"whatif-{scenario}")
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    rec.set_sinks(rr.FileSink(str(path)), default_blueprint=rrb.Blueprint(rrb.Vertical(
        rrb.Horizontal(rrb.Spatial2DView(origin="/whatif/tradeoff", name="lab-hours (up) against cost (right)"),
                       rrb.TextDocumentView(origin="/whatif/variants", name="Variants")),
        rrb.Horizontal(rrb.BarChartView(origin="/whatif/lab_hours", name="lab-hours, median"),
                       rrb.BarChartView(origin="/whatif/cost", name="cost, median"),
                       *[rrb.BarChartView(origin=f"/whatif/utilisation/{t}", name=f"{t} busy, mean")
                         for t in sorted(summary[0]["utilisation"]) if summary]),
    )))
    hours = [row["lab_hours"][1] for row in summary]
    costs = [row["cost"][1] for row in summary]
    rec.log("whatif/tradeoff", rr.Points2D(positions=[(c, -h) for c, h in zip(costs, hours)], radii=4.0,
                                           labels=[f"{i}: {row['variant']}" for i, row in enumerate(summary)]),
            static=True)
    rec.log("whatif/lab_hours", rr.BarChart(np.asarray(hours, dtype=np.float64)), static=True)
    rec.log("whatif/cost", rr.BarChart(np.asarray(costs, dtype=np.float64)), static=True)
    for t in sorted(summary[0]["utilisation"]) if summary else []:
        values = [100 * row["utilisation"].get(t, 0.0) for row in summary]
        rec.log(f"whatif/utilisation/{t}", rr.BarChart(np.asarray(values, dtype=np.float64)), static=True)
    lines = [f"# {scenario}: what if", "", "| # | variant | lab-h (median) | cost (median) | busiest |", "|---|---|---|---|---|"]
    lines += [f"| {i} | {row['variant']} | {row['lab_hours'][1]:.2f} | {row['cost'][1]:,.0f} | {row['bottleneck']} |"
              for i, row in enumerate(summary)]
    rec.log("whatif/variants", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)
    rec.flush()
    rec.disconnect()
