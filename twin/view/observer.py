"""From the lab's messages to what a person watches: device states, queue, spectra, objective, log.

The observer sees only what any bus subscriber sees — device events and
telemetry, and the orchestrator's decisions — so the same code serves a
recorder in the campaign's process, ``twin watch`` in another one, and
``twin replay`` reading the journal. It draws on a ``Canvas`` (the Rerun
recorder implements it) and imports nothing of Rerun itself.
"""

from __future__ import annotations

import functools
import logging
import math
from typing import Any, Protocol

from twin.campaign.events import Note
from twin.campaign.summary import summary_markdown
from twin.core.messages import json_from_wire
from twin.view.repeats import Repeats

#: A device's states, in the order the viewer lists them.
STATES = ("offline", "idle", "failed", "quarantined", "busy")
WARN_KINDS = {"attempt.failed", "task.retry", "scheduler.invalid", "message.invalid", "result.late",
              "device.flapping", "devices.unavailable", "devices.missing", "campaign.stopping", "attempt.cancelled",
              "operator.pause", "operator.abort", "operator.stop", "operator.refused", "question.asked",
              "question.withdrawn", "consumable.low", "output.unscored", "planner.invalid", "device.clock_off",
              "scheduler.stalled", "device.refusing", "device.mismatch",
              "device.elsewhere", "device.misnamed"}
ERROR_KINDS = {"message.rejected", "device.quarantined", "device.stuck", "device.lost", "experiment.abandoned",
               "consumable.depleted", "planner.failed"}
log = logging.getLogger(__name__)
QUEUE_SERIES = ("ready steps", "samples waiting", "oldest sample's age (h)")
#: Telemetry series a viewer draws of one device at most: a driver that names a reading afresh each time would make
#: one each.
MAX_TELEMETRY_SERIES = 256
#: What an observer draws of a device's messages (an in-process runtime hands it only these).
WATCHED = frozenset({"result", "telemetry"})
#: Decisions drawn elsewhere and not repeated in the text log.
QUIET = {"campaign.summary", "campaign.started", "task.ready", "attempt.running", "attempt.done",
         "experiment.proposed"}
#: Decisions an observer neither draws nor logs: an in-process runtime need not hand them over.
UNDRAWN = frozenset({"attempt.running"})
DEBUG_KINDS = {"task.ready", "attempt.dispatched", "attempt.running", "attempt.done"}


@functools.lru_cache(maxsize=4096)  # per output and target of every result drawn: the names are few
def part(name: str) -> str:
    """``name`` as one part of an entity path, escaped as Rerun escapes it (``rr.escape_entity_path_part``, which this
    module does without Rerun): a driver's reading named 'a/b' was drawn as an entity b inside a, one named 'sp ace'
    had Rerun warn on the terminal, and one named '' was drawn on the device's own entity."""
    if not name:
        return '\\"\\"'  # "", as text
    return "".join(c if c.isalnum() or c in "_-." else "\\" + c if c.isascii() and c.isprintable()
                   else f"\\u{{{ord(c):04X}}}" for c in name)


class Canvas(Protocol):
    def scalar(self, path: str, t: float, value: float, seq: int | None = None) -> None: ...

    def scalars(self, path: str, t: float, values: tuple[float, ...], names: tuple[str, ...]) -> None:
        """Several series of one panel in one row (``names`` label them)."""

    def state(self, path: str, t: float, state: str) -> None: ...

    def text(self, path: str, t: float, text: str, level: str) -> None: ...

    def line(self, path: str, t: float, points: Any, seq: int | None = None) -> None:
        """A polyline: a list of (x, y) or an (N, 2) array."""

    def curve(self, path: str, t: float, x0: float, dx: float, y: list, seq: int | None = None) -> None:
        """A polyline over evenly spaced x: (x0 + i·dx, y[i]); a curve whose y are not all numbers is not drawn."""

    def points(self, path: str, t: float, points: list[tuple[float, ...]], seq: int | None = None) -> None: ...

    def document(self, path: str, markdown: str, t: float | None = None) -> None:
        """A markdown panel; with ``t``, this version of it from lab time ``t`` on."""

    def image(self, path: str, t: float, png: bytes) -> None: ...

    def flush(self) -> None:
        """Send what is buffered: live viewers call this now and then."""


def drawable(payload: bytes | str) -> dict[str, Any] | None:
    """A bus message parsed, or None for one with nothing to draw (accepted, progress — skipped before the parse
    to keep watching cheap) or one that is not a message (the orchestrator logs those; a watcher skips them)."""
    head = payload[:40]
    if isinstance(head, bytes) and (b'"kind":"accepted"' in head or b'"kind":"progress"' in head):
        return None
    try:
        env = json_from_wire(payload)
        float(env["t_lab"])
    except (ValueError, KeyError, TypeError):
        return None
    return env if isinstance(env, dict) else None


def _stock_path(stock: str) -> str:
    """An item's stock, or an instance's own (``vials@spectrometer-2``: drawn under the item)."""
    return "consumables/" + stock.replace("@", "/")


def _level(what: str) -> str:
    return "ERROR" if what in ERROR_KINDS else "WARN" if what in WARN_KINDS else "DEBUG" if (
        what in DEBUG_KINDS) else "INFO"


def _shown(value: Any) -> str:
    """A value in a log line: floats to six figures (a back-off of 131.741 s, not 131.74149491155254), an object's
    too."""
    if type(value) is float:
        return f"{value:.6g}"
    if type(value) is dict:
        return "{" + ", ".join([f"{k}: {_shown(v)}" for k, v in value.items()]) + "}"
    return str(value)


def _experiment_of(task: str | None) -> int | None:
    if task and task.startswith("e") and "s" in task:
        try:
            return int(task[1:].split("s")[0])
        except ValueError:
            return None
    return None


class LabObserver:
    def __init__(self, canvas: Canvas, dedupe: bool = False) -> None:
        self.c = canvas
        self.info: dict[str, Any] = {}
        self.state: dict[str, str] = {}
        self.busy_since: dict[str, float] = {}
        self.busy_total: dict[str, float] = {}
        self.ready: set[str] = set()  # the ready steps' tasks
        self.best = math.inf
        self.best_by_target: dict[str, float] = {}
        self.finished = 0
        self.t0: float | None = None
        self.spectra = 0
        self.undrawn = 0  # messages and decisions the viewer could not draw
        self.undrawn_series = 0  # readings of names past a device's MAX_TELEMETRY_SERIES
        self._series_of: dict[str, int] = {}  # a device's telemetry series so far
        self._too_many: set[str] = set()  # devices said to have more
        self.done = False
        self._last_queue: tuple | None = None
        self._queue_at: float | None = None  # the queue changed at this lab time; drawn when time moves on
        self._made: dict[str, float] = {}  # ready steps whose sample exists: when it was made
        self._seen: Repeats | None = Repeats() if dedupe else None
        self._route: Any = None  # a RouteView, once a synthesis route runs
        self._kinds: dict[str, tuple[Any, str | None]] = {}  # a decision's handler and its log level (None: unlogged)
        self._paths: dict[str, tuple[str, str]] = {}  # a device's state and utilisation entities
        self._target_outputs: set[str] = set()
        self._telemetry_paths: dict[tuple[str, str], str] = {}

    # -- input ------------------------------------------------------------
    def on_message(self, key: str, payload: bytes | str) -> None:
        env = drawable(payload)
        if env is not None:
            self.on_decoded(env)

    def on_decoded(self, env: dict[str, Any]) -> None:
        """A message off the bus, parsed: drawn unless seen before."""
        if env.get("body", {}).get("what") != "decisions" and not self._fresh(env):
            return
        self.on_envelope(env)

    def on_envelope(self, env: dict[str, Any]) -> None:
        """A message already decoded: what an in-process runtime hands over, without a second parse. What cannot
        be drawn is skipped and logged: the viewer never stops a campaign."""
        try:
            self._envelope(env)
        except Exception as exc:
            self._not_drawn(f"a {env.get('kind')} message from {env.get('sender')}", exc)

    def _not_drawn(self, what: str, exc: Exception) -> None:
        self.undrawn += 1
        if self.undrawn <= 10:
            log.warning("viewer: could not draw %s (%r); the campaign goes on without it in the viewer", what, exc)

    def _envelope(self, env: dict[str, Any]) -> None:
        kind, t = env["kind"], float(env["t_lab"])
        if self.t0 is None:
            self.t0 = t
        if kind == "decision":
            body = env.get("body", {})
            if body.get("what") == "decisions":  # a turn's worth of decisions in one message
                for item in body.get("detail", {}).get("items", []):
                    if self._fresh(item):
                        self.on_decision(float(item["t_lab"]), item.get("what", ""), item.get("detail", {}))
            else:
                self.on_decision(t, body.get("what", ""), body.get("detail", {}))
        elif kind == "telemetry":
            sender, paths = env["sender"], self._telemetry_paths
            for name, value in env.get("body", {}).get("readings", {}).items():
                path = paths.get((sender, name))
                if path is None:
                    drawn = self._series_of.get(sender, 0)
                    if drawn >= MAX_TELEMETRY_SERIES:
                        self._too_many_series(sender, name)
                        continue
                    self._series_of[sender] = drawn + 1
                    path = paths[sender, name] = f"telemetry/{sender}/{part(name)}"
                self.c.scalar(path, t, float(value))
        elif kind == "result":
            self._spectrum(t, env)

    def _too_many_series(self, sender: str, name: str) -> None:
        if sender not in self._too_many and len(self._too_many) < 10:
            self._too_many.add(sender)
            log.warning("viewer: %s's reading %r would be its telemetry series number %d, over the %d a viewer draws "
                        "of one device (a driver naming its readings afresh, with a time or a counter in the name?): "
                        "its readings of new names are not drawn, and the journal has them all", sender,
                        str(name)[:80], MAX_TELEMETRY_SERIES + 1, MAX_TELEMETRY_SERIES)
        self.undrawn_series += 1

    def _fresh(self, message: dict[str, Any]) -> bool:
        """False for a message drawn before (a watcher gets some twice: in the history and live)."""
        return self._seen is None or self._seen.fresh(message.get("id"), message.get("t_lab"))

    def on_decision(self, t: float, what: str, d: dict[str, Any]) -> None:
        """A decision as the bus carries it: ``d`` holds experiment, task, attempt, device and info."""
        self.on_note(Note(t, what, d.get("experiment"), d.get("task"), d.get("attempt"), d.get("device"),
                          d.get("info")))

    def on_note(self, n: Note) -> None:
        """A decision as the core noted it: what an in-process runtime hands over, without building a message."""
        try:
            self._note(n)
        except Exception as exc:
            self._not_drawn(f"the decision {n.kind} {n.task or ''}", exc)

    def _note(self, n: Note) -> None:
        t, what = n.t_lab, n.kind
        if self.t0 is None:
            self.t0 = t
        if self._queue_at is not None and t != self._queue_at:
            self._draw_queue()
        if what in UNDRAWN:
            return
        info = n.detail
        kind = self._kinds.get(what)
        if kind is None:  # looked up once per kind of decision: thousands of decisions, a dozen kinds
            kind = self._kinds[what] = (getattr(self, "_" + what.replace(".", "_"), None),
                                        None if what in QUIET else _level(what))
        handler, level = kind
        if handler is not None:
            handler(t, n, info)
        if level is not None:
            text = what
            if n.task:
                text = f"{text} {n.task}"
            elif n.experiment is not None:  # experiment.done, .abandoned: which one
                text = f"{text} e{n.experiment}"
            if n.attempt:
                text = f"{text} #{n.attempt}"
            if n.device:
                text = f"{text} on {n.device}"
            self.c.text("log", t, text + self._describe(info) if info is not None else text, level)

    def finish(self) -> None:
        """Draw what waits for lab time to move on (the queue's last change); a recording calls this on close."""
        if self._queue_at is not None:
            self._draw_queue()

    @staticmethod
    def _describe(info: Any) -> str:
        if info is None:
            return ""
        if isinstance(info, dict):
            text = ", ".join([f"{k}={_shown(v)}" for k, v in info.items()
                              if v not in (None, "", {}) and (v or k not in ("outputs", "scores"))])
            return f": {text}" if text else ""
        return f": {info}"

    # -- decisions ----------------------------------------------------------
    def _campaign_started(self, t: float, n: Note, info: dict) -> None:
        self.info = info or {}
        self._target_outputs = {name for target in self.info.get("targets", []) for name in target.get("outputs", {})}
        for name in self.info.get("devices", {}):
            self._set_state(t, name, "offline")
        lines = []
        for target in self.info.get("targets", []):
            cond = target.get("outputs", {}).get("peak_nm")
            if cond and cond.get("value") is not None:
                lines.append(cond["value"])
        for i, nm in enumerate(lines):
            self.c.line(f"spectra/targets/{i}", t, [(nm, 0.0), (nm, 1.2)])
        self.c.text("log", t, f"campaign {self.info.get('scenario', '?')} started: "
                    f"{len(self.info.get('devices', {}))} devices, budget {self.info.get('budget')}", "INFO")

    def _experiment_proposed(self, t: float, n: Note, params: dict) -> None:
        if isinstance(params, dict) and "reaction" in params:  # a synthesis route's reaction
            if self._route is None:
                from twin.view.route_view import RouteView

                self._route = RouteView(self.c)
            self._route.proposed(t, n.experiment, params)
            return
        box = self.info.get("parameters", {})
        coords = []
        numbers = [(k, v) for k, v in (params or {}).items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
        for name, value in numbers[:3]:
            lo, hi = (box.get(name) or [0.0, 1.0])[:2]
            coords.append((float(value) - lo) / (hi - lo) if hi > lo else float(value))
        coords += [0.0] * (3 - len(coords))
        self.c.points("planner/proposals", t, [tuple(coords)], seq=n.experiment)

    def _task_ready(self, t: float, n: Note, info: dict) -> None:
        made = (info or {}).get("sample_made")
        self.ready.add(n.task)
        if made is not None:
            self._made[n.task] = made
        self._queue_at = t

    def _consumable_refilled(self, t: float, n: Note, info: dict) -> None:
        self.c.scalar(_stock_path(info["item"]), t, float(info["level"]))

    _consumable_returned = _consumable_refilled

    def _attempt_dispatched(self, t: float, n: Note, info: Any) -> None:
        if self._route is not None:
            self._route.running(t, n.experiment, n.device)
        for item, level in ((info or {}).get("left") or {}).items():
            self.c.scalar(_stock_path(item), t, float(level))
        self.ready.discard(n.task)
        self._made.pop(n.task, None)
        self._queue_at = t
        self._set_state(t, n.device, "busy")

    def _attempt_done(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "idle")

    def _attempt_failed(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "failed")

    def _attempt_cancelled(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "idle")

    def _device_quarantined(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "quarantined")

    def _device_probe(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "idle" if self.state.get(n.device) != "offline" else "offline")

    def _device_online(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "idle")

    def _device_lost(self, t: float, n: Note, info: Any) -> None:
        self._set_state(t, n.device, "offline")

    def _experiment_done(self, t: float, n: Note, info: dict) -> None:
        if self._route is not None:
            self._route.finished(t, n.experiment, (info or {}).get("outputs") or {})
        self.finished += 1
        seq = n.experiment
        scores = (info or {}).get("scores") or {}
        finite = [s for s in scores.values() if s is not None and math.isfinite(s)]
        if finite:
            score = min(finite)
            self.best = min(self.best, score)
            self.c.scalar("objective/score", t, score, seq=seq)
            self.c.scalar("objective/best", t, self.best, seq=seq)
        for name, s in scores.items() if len(scores) > 1 else ():  # one target: its series would be the above
            if s is None or not math.isfinite(s):
                continue
            self.best_by_target[name] = min(self.best_by_target.get(name, math.inf), s)
            self.c.scalar(f"objective/targets/{part(name)}/score", t, s, seq=seq)
            self.c.scalar(f"objective/targets/{part(name)}/best", t, self.best_by_target[name], seq=seq)
        for name, value in ((info or {}).get("outputs") or {}).items():
            if name in self._target_outputs:
                self.c.scalar(f"objective/outputs/{part(name)}", t, float(value), seq=seq)
        self.c.scalar("campaign/finished", t, float(self.finished), seq=seq)

    def _experiment_abandoned(self, t: float, n: Note, info: Any) -> None:
        if self._route is not None:
            self._route.finished(t, n.experiment, None, str((info or {}).get("reason", "")))
        self.finished += 1
        self.c.scalar("campaign/finished", t, float(self.finished), seq=n.experiment)

    def _experiment_reopened(self, t: float, n: Note, info: Any) -> None:
        self.finished -= 1  # an operator's retry: abandoned, and now in the lab again
        self.c.scalar("campaign/finished", t, float(self.finished), seq=n.experiment)

    def _campaign_summary(self, t: float, n: Note, summary: dict) -> None:
        self.done = True
        self.finish()
        self.c.document("summary", summary_markdown(summary or {}))
        self.c.flush()

    # -- derived series -----------------------------------------------------
    def _set_state(self, t: float, device: str | None, state: str) -> None:
        if not device:
            return
        was = self.state.get(device)
        if was == "busy":
            self.busy_total[device] = self.busy_total.get(device, 0.0) + t - self.busy_since.pop(device, t)
        if state == "busy":
            self.busy_since[device] = t
        self.state[device] = state
        paths = self._paths.get(device)
        if paths is None:
            paths = self._paths[device] = (f"devices/{device}", f"utilisation/{device}")
        self.c.state(paths[0], t, state)
        elapsed = t - (self.t0 or 0.0)
        if was == "busy" and elapsed > 0:
            self.c.scalar(paths[1], t, self.busy_total.get(device, 0.0) / elapsed)

    def _draw_queue(self) -> None:
        """One row per lab time at which the queue changed (several changes at one instant show as the last)."""
        t, made = self._queue_at, self._made
        self._queue_at = None
        now = (float(len(self.ready)), float(len(made)), min(made.values()) if made else None)
        if now == self._last_queue:
            return
        self._last_queue = now
        self.c.scalars("queue", t, (now[0], now[1], (t - now[2]) / 3600 if made else 0.0), QUEUE_SERIES)

    def _spectrum(self, t: float, env: dict) -> None:
        outputs = env["body"].get("outputs")
        spec = outputs.get("spectrum") if type(outputs) is dict else None
        if type(spec) is not dict:
            return
        y = spec.get("y")
        if type(y) is not list or not y:
            return
        try:
            start, step = float(spec.get("start_nm", 0.0)), float(spec.get("step_nm", 1.0))
        except (TypeError, ValueError):
            return
        seq = _experiment_of(env.get("task"))
        self.spectra += 1
        self.c.curve("spectra/measurement", t, start, step, y, seq=seq)
        peak, intensity = outputs.get("peak_nm"), outputs.get("intensity")
        if isinstance(peak, (int, float)) and isinstance(intensity, (int, float)):
            self.c.points("spectra/peak", t, [(float(peak), float(intensity))], seq=seq)
