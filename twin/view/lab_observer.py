"""A lab that several campaigns share, on one recording.

The lab's devices are drawn once, at the top (``devices/``, ``utilisation/``,
``telemetry/``, ``consumables/``), from every campaign's notes: a device holds
one campaign's step at a time, so their notes tell one story. Each campaign's
own panels — objective, queue, spectra, proposals, log, summary, and its own
use of the devices — go under ``campaigns/<name>/``, drawn by a
``CampaignObserver`` of its own. The same observer serves the recorder in the
lab's process (handed notes and decoded messages) and ``twin watch`` in another
one (handed the bus's messages).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from twin.campaign.events import Note
from twin.view.observer import Canvas, LabObserver, drawable

#: The decisions that change what a device is doing, whichever campaign notes them.
DEVICE_KINDS = frozenset({"attempt.dispatched", "attempt.done", "attempt.failed", "attempt.cancelled",
                          "device.quarantined", "device.probe", "device.online", "device.lost",
                          "consumable.refilled", "consumable.returned"})


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

    def curve(self, path: str, t: float, x0: float, dx: float, y: list, seq: int | None = None) -> None:
        self.c.curve(self.p + path, t, x0, dx, y, seq)

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

    def _note(self, n: Note) -> None:
        if n.kind not in DEVICE_KINDS:
            return
        if self.t0 is None:
            self.t0 = n.t_lab
        getattr(self, "_" + n.kind.replace(".", "_"))(n.t_lab, n, n.detail)

    def _draw_queue(self) -> None:
        """The queues are the campaigns' own."""
        self._queue_at = None


class CampaignObserver(LabObserver):
    """One campaign of a shared lab: its panels under ``campaigns/<name>/``; its device notes and the devices'
    telemetry also go to the lab's panels."""

    def __init__(self, lab: SharedLabObserver, name: str, dedupe: bool = False) -> None:
        super().__init__(PrefixedCanvas(lab.c, f"campaigns/{name}/"), dedupe)
        self.lab = lab

    def _note(self, n: Note) -> None:
        super()._note(n)
        if n.kind in DEVICE_KINDS:
            self.lab.devices.on_note(n)
        elif n.kind == "campaign.started":
            self.lab.meet(n.t_lab, (n.detail or {}).get("devices") or {})
            for device, state in self.lab.devices.state.items():  # a campaign that comes later finds them there
                if state != "offline":
                    self._set_state(n.t_lab, device, "idle")

    def on_envelope(self, env: dict[str, Any]) -> None:
        if env.get("kind") != "telemetry":
            super().on_envelope(env)
        elif self.lab.devices._fresh(env):  # a watcher hears it live and in a campaign's history
            self.lab.devices.on_envelope(env)


class SharedLabObserver:
    def __init__(self, canvas: Canvas, devices: dict[str, str] | None = None, t0: float = 0.0,
                 dedupe: bool = False, on_campaign: Callable[[list[str]], None] | None = None) -> None:
        """``devices``: instance name → device type, every device of the lab (a watcher learns them from the
        campaigns as they start). ``dedupe``: drop messages seen before (a watcher gets some twice).
        ``on_campaign``: told the campaigns so far when one more appears (the recording's layout follows)."""
        self.c = canvas
        self.devices = LabDevices(canvas, dedupe=dedupe)
        self.campaigns: dict[str, CampaignObserver] = {}
        self._dedupe, self._on_campaign = dedupe, on_campaign
        if devices:
            self.meet(t0, devices)

    def meet(self, t: float, devices: dict[str, str]) -> None:
        """Devices of the lab seen for the first time: offline until they are heard from."""
        for name in devices:
            if name not in self.devices.state:
                if self.devices.t0 is None:
                    self.devices.t0 = t
                self.devices._set_state(t, name, "offline")

    def campaign(self, name: str) -> CampaignObserver:
        seen = self.campaigns.get(name)
        if seen is None:
            seen = self.campaigns[name] = CampaignObserver(self, name, self._dedupe)
            if self._on_campaign is not None:
                self._on_campaign(list(self.campaigns))
        return seen

    def on_envelope(self, env: dict[str, Any]) -> None:
        """A device's message the lab decoded: telemetry to the lab's panels, a result to its campaign's."""
        if env.get("kind") == "telemetry":
            self.devices.on_envelope(env)
            return
        seen = self.campaigns.get(env.get("campaign") or "")
        if seen is not None:  # a result for none of the campaigns: the campaign it names rejects it
            seen.on_envelope(env)

    def on_message(self, key: str, payload: bytes | str) -> None:
        """A device's message off the bus (``twin watch``); campaigns' decisions go to ``campaign(name)``."""
        env = drawable(payload)
        if env is None:
            return
        if env.get("kind") == "telemetry":
            if self.devices._fresh(env):
                self.devices.on_envelope(env)
            return
        seen = self.campaigns.get(env.get("campaign") or "")
        if seen is not None:
            seen.on_decoded(env)

    @property
    def spectra(self) -> int:
        return sum(c.spectra for c in self.campaigns.values())

    @property
    def finished(self) -> int:
        return sum(c.finished for c in self.campaigns.values())

    @property
    def done(self) -> bool:
        """Every campaign seen so far has ended."""
        return bool(self.campaigns) and all(c.done for c in self.campaigns.values())

    def finish(self) -> None:
        for seen in self.campaigns.values():
            seen.finish()
