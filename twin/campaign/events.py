"""The core's vocabulary: the events it takes and the actions it returns.

Events come from devices (through a runtime that decoded them), presence,
timers the core set, the planner's and scheduler's answers, an operator's
acts and a stop request. Actions tell the runtime what to do: send, time, ask, record.
All are small frozen records; nothing here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from twin.core.counts import quantity
from twin.campaign.decisions import Assignment, LabView, Outcome, Proposal
from twin.core.messages import SAFING, Kind


class Status(StrEnum):
    PENDING = "pending"
    RUNNING = "running"
    DONE = "done"
    ABANDONED = "abandoned"


class Code(StrEnum):
    """How an attempt ended."""

    OK = "ok"
    FAILED = "failed"
    TIMED_OUT = "timed_out"
    DEVICE_LOST = "device_lost"
    REJECTED = "rejected"
    CANCELLED = "cancelled"
    DRIVER_ERROR = "driver_error"


#: Notes a runtime also logs as warnings (``alert_text``), on the ``ALERT_LOGGER`` logger: the lab cannot go on as
#: it is, or a device sends what the campaign cannot use.
ALERTS = frozenset({"devices.unavailable", "devices.missing", "device.flapping", "device.stuck", "device.refusing",
                    "output.unscored", "scheduler.stalled", "consumable.depleted", "device.mismatch",
                    "device.elsewhere", "device.misnamed"})
ALERT_LOGGER = "twin.alerts"
#: notes a runtime on a live clock also logs (``AlertLog.presence``): a device gone from the bus, and back; one set
#: aside for failing; a device type said unusable (``devices.unavailable``) usable again
PRESENCE = frozenset({"device.lost", "device.online", "device.quarantined", "devices.available"})
#: notes after which a runtime tells its ``on_progress`` (a progress line): work finished, a device type gone, an
#: operator's act
PROGRESS_KINDS = ("attempt.done", "attempt.failed", "devices.", "operator.")


class TimerKind(StrEnum):
    STARTUP = "startup"
    LIMIT = "limit"
    DEADLINE = "deadline"
    RETRY = "retry"
    PROBE = "probe"
    CANCEL_GRACE = "cancel_grace"
    GIVE_UP = "give_up"  # no usable instance of a device type: abandon what waits for it
    QUESTION = "question"  # an operator's question unanswered: its default applies
    ANSWER = "answer"  # virtual time: the scenario's simulated operator answers
    REFILL = "refill"  # virtual time: the scenario's simulated operator refills a consumable
    CONFIRM = "confirm"  # virtual time: the scenario's simulated operator confirms a human step
    SUBMIT = "submit"  # a shared lab: a campaign's start_h has come


@dataclass(frozen=True, slots=True)
class TimerKey:
    kind: TimerKind
    ref: str = ""  # the task, "task#attempt", or device it is about


# -- events -----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceMessage:
    """A decoded message from a device: accepted, progress, result, fault, rejected or telemetry.

    ``device`` is the sender the message names; ``key`` the device whose key it arrived on; ``token`` the
    attempt token it carries. The core counts it only if all three agree with the attempt it is about."""

    kind: Kind
    device: str
    task: str
    attempt: int
    body: dict[str, Any]
    payload: Any  # what the journal stores (never the token): the bytes received, or an envelope dict
    key: str = ""  # "" = the sender's own key (the fast runtime's in-process devices)
    token: str = ""
    campaign: str = ""  # the campaign the envelope names: which campaign of a shared lab it is for


@dataclass(frozen=True, slots=True)
class InvalidInput:
    """A message that could not be decoded (oversized, not JSON, wrong fields): counted, never raised."""

    sender: str
    reason: str
    key: str = ""
    excerpt: str = ""  # the start of the payload, for the journal
    count: int = 1  # the messages it stands for: a journal's run of them, replayed as one (floods.py)


@dataclass(frozen=True, slots=True)
class Presence:
    device: str
    alive: bool


@dataclass(frozen=True, slots=True)
class TimerFired:
    key: TimerKey


@dataclass(frozen=True, slots=True)
class Stop:
    """``outside``: the stop came from outside the campaign (a signal, an operator, a caller's ``stop``), and
    ``twin resume`` continues the campaign; otherwise it is the campaign's own end (its lab hours spent, a stall),
    which a resume would only meet again."""

    reason: str
    outside: bool = False


@dataclass(frozen=True, slots=True)
class Operator:
    """An operator's act (``twin ctl``): ``pause`` (``now``: cancel what is in the lab to a safe state too),
    ``resume``, ``abort`` or ``retry`` an ``experiment``, ``stop``, ``answer`` a ``question`` with an ``option``,
    ``refill`` a consumable ``item`` (by ``amount``, or to its starting level), ``confirm`` a human step's ``task``. ``ref`` names the request (the runtime
    answers the operator with the note that carries it) and orders acts of one instant as they arrived."""

    command: str
    who: str
    ref: str = ""
    experiment: int | None = None
    now: bool = False
    reason: str = ""
    question: str = ""  # answer: the question's id
    option: str = ""  # answer: the option chosen
    item: str = ""  # refill: the consumable
    amount: float | None = None  # refill: how much (None: to its starting level)
    task: str = ""  # confirm: the human step done


OPERATOR_COMMANDS = ("pause", "resume", "abort", "retry", "stop", "answer", "refill", "confirm")


@dataclass(frozen=True, slots=True)
class Proposed:
    """The planner's answer to an ``Ask`` of kind ``plan``; ``failed``: why the planner can propose no more
    (it raised, or answered something else than proposals); ``why``: with no proposals, the planner's own word on
    why it has none (its ``why_no_more``)."""

    proposals: list[Proposal]
    failed: str = ""
    why: str = ""


@dataclass(frozen=True, slots=True)
class Decided:
    """The scheduler's answer to an ``Ask`` of kind ``schedule``; ``wall_s`` is how long it took."""

    assignments: list[Assignment]
    wall_s: float = 0.0


# -- actions ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Send:
    device: str
    kind: Kind  # command or cancel
    task: str
    attempt: int
    body: dict[str, Any]
    token: str = ""  # the attempt's token: the device echoes it, and obeys a cancel only with it


@dataclass(frozen=True, slots=True)
class SetTimer:
    key: TimerKey
    delay: float


@dataclass(frozen=True, slots=True)
class CancelTimer:
    key: TimerKey


@dataclass(frozen=True, slots=True)
class Ask:
    """Ask the planner (``plan``: n, history, pending) or the scheduler (``schedule``: view)."""

    what: str
    n: int = 0
    history: tuple[Outcome, ...] = ()
    pending: tuple[dict[str, Any], ...] = ()
    view: LabView | None = None


@dataclass(frozen=True, slots=True)
class Note:
    """A state change: a journal row, and a decision for watchers."""

    t_lab: float
    kind: str
    experiment: int | None = None
    task: str | None = None
    attempt: int | None = None
    device: str | None = None
    detail: Any = None


@dataclass(frozen=True, slots=True)
class RecordMessage:
    """A message received, for the journal (``msg.<kind>``)."""

    t_lab: float
    kind: str
    experiment: int | None
    task: str | None
    attempt: int | None
    device: str | None
    payload: Any


@dataclass(frozen=True, slots=True)
class RecordExperiment:
    experiment: Any  # ledger.Experiment; its row is taken when the action is performed
    final: bool = False  # it just finished: a live runtime writes it to disk at once


@dataclass(frozen=True, slots=True)
class Finished:
    """The campaign is over; the ledger holds its final state."""

    reason: str


Event = DeviceMessage | InvalidInput | Presence | TimerFired | Operator | Stop
Action = Send | SetTimer | CancelTimer | Ask | Note | RecordMessage | RecordExperiment | Finished


def alert_text(n: Note) -> str:
    """An alert's line in the log: what, on which device or experiment, and the detail."""
    if n.kind == "consumable.depleted" and isinstance(n.detail, dict):  # on a live clock, a person must refill it
        d = n.detail
        others = "@" in str(d.get("item")) and d.get("stocks", 2) > 1  # an instance's own stock, and others have one
        elsewhere = "go to another instance that has some, or " if others else ""
        return (f"{d.get('item')} is out ({quantity(d.get('level', 0), str(d.get('unit', '')))} left, "
                f"{quantity(d.get('needed', 0), str(d.get('unit', '')))} needed "
                f"by {n.task}): its steps {elsewhere}wait for `twin ctl refill {d.get('item')}` (in virtual time, its "
                "simulate_refill)")
    where = f" {n.device}" if n.device else f" (experiment {n.experiment})" if n.experiment is not None else ""
    return f"{n.kind}{where}: {_alert_words(n)}"


#: How a device type's instances became unusable (True: people, who are not lost: one whose steps nobody confirmed
#: in time is set aside as a failing device is).
UNUSABLE = {False: "lost or quarantined",
            True: "away, or set aside after steps nobody confirmed in time: `twin ctl confirm` confirms one"}


def _alert_words(n: Note) -> str:
    """A detail written for a person: what happened, what the lab does about it, and what one can do."""
    d = n.detail
    if n.kind == "devices.unavailable" and isinstance(d, dict):
        ids = [str(e) for e in d.get("experiments", ())]
        waiting = ", ".join(ids[:10]) + (f" and {len(ids) - 10} more" if len(ids) > 10 else "")
        waits = f"experiment {waiting} waits for one, and is" if len(ids) == 1 else \
            f"experiments {waiting} wait for one, and are"
        return (f"no {d.get('type')} is usable (each {UNUSABLE[bool(d.get('people'))]}); {waits} abandoned if none "
                f"is back within {d.get('give_up_after_s', 0):g} lab-s (campaign.give_up_after_s); a quarantined "
                f"one is given work again after orchestrator.probe_after_s")
    if n.kind == "devices.missing" and isinstance(d, list):
        one = len(d) == 1
        return (f"{', '.join(map(str, d))} not on the bus within orchestrator.startup_s: the campaign starts without "
                f"{'it' if one else 'them'}, and {'it' if one else 'each'} takes work once its driver joins the bus "
                "(one in another process: `twin device serve`, connected to the lab's address; one whose driver "
                "connects to its instrument: once the instrument answers, as the driver's own lines say)")
    if n.kind == "device.mismatch" and isinstance(d, dict):
        found = "; ".join(map(str, d.get("differences", ()))) + (f"; and {d.get('more')} more" if d.get("more") else "")
        return (f"served by a process whose scenario differs from this lab's: {found}. The lab expects its steps, "
                f"and sets their deadlines, by this lab's file, and the device runs them by its own: serve it from the "
                f"same file (`twin device serve LAB.yaml --id {n.device}`)")
    if n.kind == "device.elsewhere" and isinstance(d, dict):
        labs = ", ".join(repr(lab) for lab in d.get("labs", ()))
        return (f"not on the bus as a device of lab {d.get('lab')!r}, but on it as a device of lab {labs}: its process "
                f"was given another lab file (its `lab:` field) or --set lab=…; serve it with this lab's file "
                f"(`twin device serve LAB.yaml --id {n.device}`); a device of your own puts lab {d.get('lab')!r} in "
                f"its keys (docs/wire.md)")
    if n.kind == "device.misnamed" and isinstance(d, dict):
        names, lab = [str(x) for x in d.get("names", ())], d.get("lab")
        which = (f"{names[0]} is, which is" if len(names) == 1 else f"{', '.join(names)} are, which are")
        return (f"not on the bus, but {which} no device of lab {lab!r}: a device of lab {lab!r} named {n.device} "
                f"declares labtwin/{lab}/alive/{n.device} and takes its commands on labtwin/{lab}/dev/{n.device}/cmd "
                f"(a type of one instance is named by its type, one of several by its type and -1, -2, …: "
                f"docs/wire.md)")
    if n.kind == "device.flapping" and isinstance(d, dict):
        return (f"left the bus again within {d.get('within_s', 0):g} lab-s of its last loss (a bad link, or another "
                f"process announcing its name); its running step keeps its deadline")
    if n.kind == "device.refusing" and isinstance(d, dict):
        return (f"has answered 'not now' ({str(d.get('reason', ''))[:200]}) to its last {d.get('refusals')} steps and "
                f"finished none since: busy with work of its own, or hung? Each refused step is sent again after its "
                f"back-off, to whichever instance is free, and abandoned after {d.get('max_refusals')} refusals; "
                f"`twin device health` shows what the device reports, and restarting it ends whatever holds it")
    if n.kind == "device.stuck" and isinstance(d, dict):
        reason = str(d.get('reason', ''))
        safing = reason.endswith(SAFING)  # the step ended; the driver's safe_state() is what has not
        return (f"refused work ({reason}) while still running {n.task} (attempt {n.attempt}), whose "
                f"cancel it left unanswered for over {d.get('grace_s', 0):g} lab-s (orchestrator.cancel_grace_s): "
                f"{'its driver has not made the instrument safe' if safing else 'its driver did not stop'}. It is "
                f"quarantined until it answers the cancel, and asked again every "
                f"{d.get('probe_after_s', 0):g} lab-s (orchestrator.probe_after_s). "
                + ("A driver's safe_state() must return once the instrument is safe (docs/drivers.md); "
                   if safing else "A driver must re-raise asyncio.CancelledError once the instrument is stopped "
                   "(docs/drivers.md); ")
                + "one that only needs longer to stop needs a larger orchestrator.cancel_grace_s; restarting the "
                "device ends the step")
    return str(d)
