"""A lab that several campaigns share, on one recording.

The lab's devices are drawn once, at the top (``devices/``, ``utilisation/``,
``telemetry/``, ``consumables/``), from every campaign's notes: a device holds
one campaign's step at a time, so their notes tell one story. Each campaign's
own panels — objective, queue, spectra, proposals, log, summary, and its own
use of the devices — go under ``campaigns/<name>/``, drawn by a
``LabObserver`` of its own.
"""

from __future__ import annotations

from typing import Any

from twin.campaign.events import Note
from twin.view.observer import Canvas, LabObserver

#: The decisions that change what a device is doing, whichever campaign notes them.
DEVICE_KINDS = frozenset({"attempt.dispatched", "attempt.done", "attempt.failed", "attempt.cancelled",
                          "device.quarantined", "device.probe", "device.online", "device.lost",
                          "consumable.refilled"})


class PrefixedCanvas:
    """A canvas that draws everything under ``prefix`` (one campaign's panels)."""

    def __init__(self, canvas: Canvas, prefix: str) -> None:
        self.c, self.p = canvas, prefix

    def scalar(self, path: str, t: float, value: float, seq: int | None = None) -> None:
        self.c.scalar(self.p + path, t, value, seq)

    def scalars(self, path: str, t: float, values: tuple[float, ...], names: tuple[str, ...]) -> None:
        self.c.scalars(self.p + path, t, values, names)

    def state(self, path: str, t: float, state: str) -> None:
        self.c.state(self.p + path, t, state)

    def text(self, path: str, t: float, text: str, level: str) -> None:
        self.c.text(self.p + path, t, text, level)

    def line(self, path: str, t: float, points: Any, seq: int | None = None) -> None:
        self.c.line(self.p + path, t, points, seq)

    def points(self, path: str, t: float, points: list[tuple[float, ...]], seq: int | None = None) -> None:
        self.c.points(self.p + path, t, points, seq)

    def document(self, path: str, markdown: str, t: float | None = None) -> None:
        self.c.document(self.p + path, markdown, t)

    def image(self, path: str, t: float, png: bytes) -> None:
        self.c.image(self.p + path, t, png)

    def flush(self) -> None:
        self.c.flush()


class LabDevices(LabObserver):
    """The lab's devices, from every campaign's device notes; it logs nothing (each campaign logs its own)."""

    def on_note(self, n: Note) -> None:
        if n.kind not in DEVICE_KINDS:
            return
        if self.t0 is None:
            self.t0 = n.t_lab
        getattr(self, "_" + n.kind.replace(".", "_"))(n.t_lab, n, n.detail)

    def _draw_queue(self) -> None:
        """The queues are the campaigns' own."""
        self._queue_at = None


class CampaignFeed:
    """What a runtime hands one campaign's seat as its observer: the campaign's notes and results to its own
    panels, device notes and telemetry to the lab's."""

    def __init__(self, lab: SharedLabObserver, name: str) -> None:
        self.lab = lab
        self.mine = LabObserver(PrefixedCanvas(lab.c, f"campaigns/{name}/"))
        self.c = self.mine.c

    def on_note(self, n: Note) -> None:
        self.mine.on_note(n)
        if n.kind in DEVICE_KINDS:
            self.lab.devices.on_note(n)
        elif n.kind == "campaign.started":  # a campaign that comes later finds the devices already there
            for device, state in self.lab.devices.state.items():
                if state != "offline":
                    self.mine._set_state(n.t_lab, device, "idle")

    def on_decision(self, t: float, what: str, d: dict[str, Any]) -> None:
        self.mine.on_decision(t, what, d)

    def on_envelope(self, env: dict[str, Any]) -> None:
        if env.get("kind") == "telemetry":
            self.lab.devices.on_envelope(env)
        else:
            self.mine.on_envelope(env)

    def finish(self) -> None:
        self.mine.finish()


class SharedLabObserver:
    def __init__(self, canvas: Canvas, devices: dict[str, str], t0: float = 0.0) -> None:
        """``devices``: instance name → device type, every device of the lab."""
        self.c = canvas
        self.devices = LabDevices(canvas)
        self.devices.t0 = t0
        for name in devices:
            self.devices._set_state(t0, name, "offline")
        self.feeds: dict[str, CampaignFeed] = {}

    def campaign(self, name: str) -> CampaignFeed:
        feed = self.feeds.get(name)
        if feed is None:
            feed = self.feeds[name] = CampaignFeed(self, name)
        return feed

    def on_envelope(self, env: dict[str, Any]) -> None:
        """A device's message the lab decoded: telemetry to the lab's panels, a result to its campaign's."""
        if env.get("kind") == "telemetry":
            self.devices.on_envelope(env)
            return
        feed = self.feeds.get(env.get("campaign") or "")
        if feed is not None:  # a result for none of the campaigns: the campaign it names rejects it
            feed.on_envelope(env)

    def finish(self) -> None:
        for feed in self.feeds.values():
            feed.finish()
