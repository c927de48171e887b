"""Whole labs drawn at random, so a scheduler policy learns scheduling, not one lab (``training.random_labs``).

Each lab drawn has 2–5 device types (``device_types``) with 1–6 instances each (``instances``), every type a copy
of one of the scenario's devices (its duration spread, setup, cleaning and faults) with its mean duration scaled
(``duration_scale``), run by the generic ``machine`` driver; about half the types also take an experiment's
parameter ``x`` (0 to the longest mean) seconds longer, so experiments differ as a reaction's time makes them. The workflow visits every type once in a random
order and, with probability ``revisit_p``, one of them again later (re-entrant, as a spectrometer measuring
before and after a reaction). Samples age as the scenario's do; the campaign keeps its budget and objective
weights, with as many experiments in the lab at once as it has device types up to all its instances plus that.

The candidate policy never sees step or device names, only durations, loads, ages and faults, so what it learns
on these labs carries over to a lab of those sizes it has never seen: a policy trained with random labs
records that it fits any workflow.
"""

from __future__ import annotations

import random

from twin.scenario.model import Scenario
from twin.scenario.training import RandomLabs

ANY_WORKFLOW = "*"  # in a policy's fits: trained on random workflows, so no step type is unseen
SUFFIX = "-random"


def random_lab(s: Scenario, rng: random.Random, duration: float = 1.0, fault: float = 1.0) -> Scenario:
    """A lab drawn from ``s.training.random_labs`` (or the defaults) with ``rng``; ``duration`` and ``fault`` scale
    every type (the episode's draws from ``training.duration_scale`` and ``fault_scale``)."""
    spec = s.training.random_labs or RandomLabs()
    if not s.devices or s.jobshop is not None:
        raise ValueError(f"{s.name}: random labs copy a lab's device types; a job shop's random instances come "
                         f"from training.jobshop_sizes")
    k = rng.randint(*spec.device_types)
    templates = [s.devices[name] for name in sorted(s.devices)]
    devices, total = {}, 0
    copied = [rng.choice(templates) for _ in range(k)]
    means = [(t.duration.mean_s or 60.0) * rng.uniform(*spec.duration_scale) * duration for t in copied]
    for i, t in enumerate(copied):
        n = rng.randint(*spec.instances)
        total += n
        devices[f"station{i}"] = {
            "driver": "machine",
            "instances": n,
            "steps": ["op"],
            # about half the types take longer for some experiments than for others (as a reaction's time)
            "duration": {"mean_s": means[i], "cv": t.duration.cv,
                         **({"plus_param": "x"} if rng.random() < 0.5 else {})},
            "setup_s": t.setup_s,
            "clean_s": t.clean_s,
            "faults": {"fail_p": min(0.5, t.faults.fail_p * fault), "hang_p": min(0.5, t.faults.hang_p * fault),
                       "mtbc_h": t.faults.mtbc_h / fault if t.faults.mtbc_h else 0.0,
                       "restart_s": t.faults.restart_s},
        }
    order = rng.sample(range(k), k)
    if k >= 2 and rng.random() < spec.revisit_p:
        i = rng.randrange(k - 1)
        order.insert(rng.randint(i + 2, k), order[i])  # again later, never twice in a row
    data = s.model_dump()
    data["name"] = (s.name + SUFFIX)[:64]
    data["devices"] = devices
    data["workflow"] = [{"step": "op", "device": f"station{i}"} for i in order]
    data["chemistry"] = {"model": "none", "parameters": {"x": {"low": 0, "high": max(means)}},
                         "stability_s": s.chemistry.stability_s}
    data["campaign"].update(planner="random", planner_options={}, stop_on_target=False,
                            max_in_flight=rng.randint(k, total + k))
    data["jobshop"] = None
    data["training"]["instances"] = {}  # the scenario's own device types are not this lab's
    data["consumables"] = {}  # nor its stocks, used by its steps, nor the questions its steps put to the operator
    data["orchestrator"]["recovery"] = []
    return Scenario.model_validate(data)


def held_out(s: Scenario, n: int) -> list[tuple[str, Scenario]]:
    """``n`` random labs no training run draws (another seed stream), each with a short name of its shape."""
    out = []
    for i in range(n):
        lab = random_lab(s, random.Random(f"held-out lab:{i}"))
        route = [w.device for w in lab.workflow]
        counts = "/".join(str(lab.devices[d].instances) for d in dict.fromkeys(route))
        out.append((f"random {i + 1}: {len(lab.devices)} types ×{counts}" + (", re-entrant" if len(route) > len(lab.devices) else ""),
                    lab))
    return out


def drawn_at_random(s: Scenario) -> bool:
    return s.name.endswith(SUFFIX) and all(d.driver == "machine" for d in s.devices.values())
