"""The campaign section of a scenario: how many experiments, who proposes and who schedules them, the seed, the
stopping rules, and whether the rl scheduler plays the lab ahead (``rollouts``, ``local_search``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from twin.scenario.spec import MAX_S, MAX_VALUE, Spec


class Campaign(Spec):
    budget: int = Field(default=30, ge=1, le=1_000_000, description="experiments to propose at most")
    planner: str = Field(default="random", max_length=256, description="what proposes experiments: an installed "
                         "planner (random, lhs, gp-bo, mf-gp-bo, ...; a wrong name lists them; fixed: the experiments "
                         "of planner_options.proposals, in order), rl:POLICY.zip, or 'package.module:Class'")
    scheduler: str = Field(default="fifo", max_length=256, description="what decides which ready step runs on which "
                           "free device: a rule (fifo, spt, mwkr, least-loaded, oldest-sample), cp-sat, rl:POLICY.zip, "
                           "remote (an agent on the bus) or 'package.module:Class'")
    seed: int = Field(default=0, ge=0, lt=2**63, description="every random draw of the run (durations, faults, "
                      "noise, the planner) follows from it: the same seed, the same campaign")
    max_in_flight: int = Field(default=4, ge=1, le=10_000, description="experiments in the lab at once")
    stop_on_target: bool = Field(default=True, description="stop proposing once every target is met")
    max_lab_hours: float = Field(default=10_000, gt=0, le=1e6, description="stop the campaign after this much lab "
                                 "time")
    max_cost: float | None = Field(default=None, gt=0, le=MAX_VALUE, description="stop proposing once this much "
                                   "is spent")
    planner_options: dict[str, Any] = Field(default_factory=dict, description="passed to the planner as keyword "
                                            "arguments (gp-bo: n_init, candidates, refit_every, log_scale; fixed: "
                                            "proposals, a list of {params: {...}} proposed in order)")
    scheduler_options: dict[str, Any] = Field(default_factory=dict, description="passed as keyword arguments to "
                                              "each scheduler whose constructor names them (cp-sat: time_limit_s, "
                                              "its wall seconds a decision, default 1; a rule takes none)")
    fallback_scheduler: str = Field(default="fifo", max_length=256, description="decides when a scheduler agent "
                                    "on the bus is absent, late or wrong")
    policy_fit: Literal["warn", "refuse"] = Field(default="warn", description="a scheduler policy used on a lab "
                                                  "outside the shapes it was trained on: warn, or refuse to start")
    rollouts: int = Field(default=1, ge=1, le=4096, description="the rl scheduler on a lab that runs as planned (every "
                          "experiment known, as in a job shop; durations with cv 0; no faults): play the campaign "
                          "this many times in the twin before it starts (the greedy run and the rest sampled from "
                          "the policy; a job shop's runs half backwards, beginning with their greedy run: 2 is the "
                          "greedy run each way) and keep the best run's order of steps on each device; 1: decide "
                          "greedily as the lab goes")
    rollout_search: Literal["sample", "active"] = Field(default="sample", description="how the rl scheduler plays "
                                                         "campaign.rollouts: sample (every run from the policy as "
                                                         "it is) or active (in rounds of 32, a copy of the policy "
                                                         "tuned on this lab between rounds by a policy gradient on "
                                                         "the runs played: from a few hundred rollouts up, a "
                                                         "better plan than sampling's; the policy file is not "
                                                         "changed); with rollouts 1, nothing is played ahead")
    local_search: int = Field(default=0, ge=0, le=1_000_000, description="the rl scheduler's plan of a job shop "
                              "(every experiment a fixed route, all in the lab from the start, no shelf life or "
                              "consumables): this many tabu-search swaps of two steps on "
                              "the best run's longest path (the greedy run's with rollouts 1), and the lab follows "
                              "the shortened orders (about half a second per 10,000 swaps on a 10x10 shop); 0: the "
                              "best run's orders as played")
    give_up_after_s: float = Field(default=4 * 3600, gt=0, le=MAX_S, description="lab seconds the experiments "
                                   "that need a device type wait when none of its instances is usable (lost, "
                                   "quarantined) before they are abandoned; an instance that comes back resumes them (past it, no "
                                   "experiment that needs the type is proposed, and the summary says so)")
    planner_deadline_s: float = Field(default=300, gt=0, le=MAX_S, description="lab seconds a planner may think "
                                      "(on a scaled or wall clock, in a worker thread) before the lab goes on "
                                      "without its answer; it is used when it comes")
    scheduler_deadline_ms: float = Field(default=2000, gt=0, le=3_600_000, description="wall ms a scheduler has "
                                         "per decision on a scaled or wall clock (an agent on the bus, or one in a "
                                         "worker thread); past it the fallback scheduler decides that time")

    @property
    def plays_ahead(self) -> str:
        """What asks the scheduler to play the lab ahead before it starts (``campaign.rollouts: 64``), or ''."""
        if self.rollouts > 1:
            return f"campaign.rollouts: {self.rollouts}"
        return f"campaign.local_search: {self.local_search}" if self.local_search else ""

    @property
    def decides_as_it_goes(self) -> str:
        """The setting that stops ``plays_ahead``'s asking (``campaign.rollouts: 1``)."""
        return "campaign.rollouts: 1" if self.rollouts > 1 else "campaign.local_search: 0"
