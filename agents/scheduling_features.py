"""What the RL scheduler sees and can do: a fixed-size encoding of a ``LabView``.

Fixed size, whatever the lab's shape, so one policy serves labs of different
sizes (and the same network is trained across randomised lab sizes): up to
``SLOTS`` ready steps (the longest-waiting first; more are seen only as a
count) and, for each, up to ``INSTANCES`` devices of the type it needs (by
name). Action ``q * INSTANCES + m`` starts ready step ``q`` on instance ``m``
of its type; the last action waits for the next event. A mask allows only
free, capable, not-to-be-avoided pairs, and waiting only while some device is
busy (otherwise nothing would ever happen again).

Times are divided by the scenario's typical step duration, so a lab of hours
and a job shop of seconds look alike to the network. A step's type is seen
through what a policy can carry to another lab — its expected duration, the
work left after it, and the state of the instances that can run it — not as
a one-hot of names. (Adding per-type queued work and competing steps was
tried and trained no better; see the issue notes.)
"""

from __future__ import annotations


import numpy as np

from twin import Assignment, DeviceState, LabView, ReadyStep
from twin import Scenario, time_scale

SLOTS, INSTANCES = 10, 4
STEP_FEATURES, PAIR_FEATURES, GLOBAL_FEATURES = 8, 3, 6
OBS_SIZE = SLOTS * STEP_FEATURES + SLOTS * INSTANCES * PAIR_FEATURES + GLOBAL_FEATURES
ACTIONS = SLOTS * INSTANCES + 1
WAIT = ACTIONS - 1
CLIP = 10.0


def signature(s: Scenario) -> dict:
    return {"observation_size": OBS_SIZE, "actions": ACTIONS, "slots": SLOTS, "instances": INSTANCES}


class Encoder:
    def __init__(self, scenario: Scenario) -> None:
        self.scale = time_scale(scenario)
        self.stability = scenario.chemistry.stability_s or 0.0

    def slots(self, view: LabView) -> list[ReadyStep]:
        return sorted(view.ready, key=lambda r: (r.ready_since, r.task))[:SLOTS]

    def instances(self, view: LabView, device_type: str) -> list[DeviceState]:
        return sorted((d for d in view.devices if d.device_type == device_type), key=lambda d: d.name)[:INSTANCES]

    def encode(self, view: LabView) -> tuple[np.ndarray, np.ndarray]:
        """(observation, action mask)."""
        now, k = view.now, self.scale
        steps = np.zeros((SLOTS, STEP_FEATURES), np.float32)
        pairs = np.zeros((SLOTS, INSTANCES, PAIR_FEATURES), np.float32)
        mask = np.zeros(ACTIONS, bool)
        for q, r in enumerate(self.slots(view)):
            devs = self.instances(view, r.device_type)
            usable = [d.free and d.name not in r.avoid for d in devs]
            busy_ends = [d.busy_until - now for d in devs if d.busy_until is not None]
            age = (now - r.sample_made) / self.stability if r.sample_made is not None and self.stability else 0.0
            steps[q] = [1.0, r.expected_s / k, (now - r.ready_since) / k, age, r.work_remaining_s / k,
                        sum(usable) / INSTANCES, 0.0 if any(usable) else max(0.0, min(busy_ends, default=CLIP * k)) / k,
                        float(bool(r.avoid))]
            for m, d in enumerate(devs):
                pairs[q, m] = [float(usable[m]), d.failures / (d.attempts + 1), d.busy_s / max(now, k)]
                mask[q * INSTANCES + m] = usable[m]
        n = max(len(view.devices), 1)
        busy = sum(d.busy_until is not None for d in view.devices)
        glob = np.array([busy / n, len(view.ready) / SLOTS, view.finished / max(view.budget, 1),
                         view.in_lab / max(view.budget, 1), sum(not d.online for d in view.devices) / n,
                         now / (k * 100.0)], np.float32)
        mask[WAIT] = busy > 0 or not mask[:WAIT].any()
        obs = np.concatenate([steps.ravel(), pairs.ravel(), glob])
        return np.clip(obs, -CLIP, CLIP).astype(np.float32), mask

    def decode(self, view: LabView, action: int) -> list[Assignment]:
        """The assignment an action means; an invalid one is raised, not guessed around."""
        action = int(action)
        if action == WAIT:
            return []
        q, m = divmod(action, INSTANCES)
        slots = self.slots(view)
        if q >= len(slots):
            raise ValueError(f"action {action}: there is no ready step in slot {q}")
        devs = self.instances(view, slots[q].device_type)
        if m >= len(devs) or not devs[m].free or devs[m].name in slots[q].avoid:
            raise ValueError(f"action {action}: instance {m} of {slots[q].device_type} cannot take {slots[q].task}")
        return [Assignment(slots[q].task, devs[m].name)]
