"""`rl`: a MaskablePPO policy (`twin train SCENARIO`) deciding which ready step runs on which free device.

``serve_on_bus`` makes the lab run it as an agent on the bus (``twin.runtime.remote_scheduler``):
the orchestrator asks it over Zenoh, with a deadline and the scenario's fallback rule.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from agents import candidates, scheduling_features
from twin import Assignment, LabView
from twin import PluginError
from twin import PLUGIN_CHECKS_LOGGER, load_policy, read_meta, tells_progress, why_runs_vary

if TYPE_CHECKING:
    from agents.rollout_plan import Plan, PlanFollower

log = logging.getLogger(PLUGIN_CHECKS_LOGGER)
_warned: set[str] = set()  # one warning per text: the CLI checks a scheduler before the lab builds its own
_plans: dict[tuple, "Plan"] = {}  # campaign.rollouts' plans, by policy file and lab


def encoder_for(scenario: Any, encoding: str) -> Any:
    """The encoder a policy of ``encoding`` reads its labs with."""
    if candidates.version(encoding) in candidates.WIDTHS:
        return candidates.CandidateEncoder(scenario, encoding)
    return scheduling_features.Encoder(scenario)


def _check_fit(path: Path, meta: dict, scenario: Any) -> str:
    """Why ``scenario`` is outside the shapes the policy was trained on ("" if inside, or if the policy does not
    say); per ``campaign.policy_fit`` a warning, or a refusal."""
    try:
        fits = candidates.fits_of(meta, str(path.with_suffix(".json")))
    except ValueError as exc:
        raise PluginError(str(exc)) from None
    if not fits:
        return ""
    why = candidates.outside(fits, candidates.lab_shape(scenario))
    if not why:
        return ""
    held = " (what it sees beyond the range it was judged on is held at that range's edge)" if "observed" in meta else ""
    text = (f"{path} was trained on labs unlike {scenario.name!r}: {'; '.join(why)}. It may schedule it poorly"
            f"{held}; to be sure, train one on this lab (`twin train SCENARIO --out P.zip`; its `training` section "
            f"sets the shapes drawn)")
    if scenario.campaign.policy_fit == "refuse":
        raise PluginError(text + " (campaign.policy_fit: refuse)")
    _warn_once(text)
    return text


def _warn_once(text: str) -> None:
    if text not in _warned:
        _warned.add(text)
        log.warning("%s", text)


class RlScheduler:
    serve_on_bus = True
    plays_ahead = True  # campaign.rollouts: it plays a deterministic lab ahead in the twin and follows its best run

    def __init__(self, scenario: Any = None, policy: str | None = None, **_: Any) -> None:
        if not policy or scenario is None:
            general = Path(__file__).parent / "policies" / "flaky_scheduler.zip"
            raise PluginError("the rl scheduler needs a trained policy: train one for this lab with `twin train "
                              "SCENARIO --out P.zip` (a few minutes) and name it rl:P.zip (--scheduler, --schedulers, "
                              "campaign.scheduler), or try the shipped one trained on random labs of 2-5 device types: "
                              f"rl:{general}")
        torch.set_num_threads(1)
        path = Path(policy)
        meta = read_meta(path) if path.exists() else {}
        encoding = meta.get("signature", {}).get("encoding")
        if str(encoding).startswith("candidates") and encoding not in candidates.WIDTHS:
            raise PluginError(f"{path} reads labs as {encoding}; this labtwin encodes them as {candidates.ENCODING} "
                              f"(other features or another network): retrain it with `twin train SCENARIO --agent scheduler`")
        if encoding in candidates.WIDTHS:
            sign = candidates.signature(scenario, encoding)
        else:
            sign = scheduling_features.signature(scenario)
        self.model = load_policy(path, "scheduler", sign)
        self.misfit = _check_fit(path, meta, scenario)
        self.encoder = encoder_for(scenario, encoding or "slots")
        if "observed" in meta and isinstance(self.encoder, candidates.CandidateEncoder):
            try:
                self.encoder.held = candidates.Observed.from_meta(meta["observed"], self.encoder.width,
                                                                  str(path.with_suffix(".json")))
            except ValueError as exc:
                raise PluginError(str(exc)) from None
        self.sees_campaigns = candidates.WIDTHS.get(encoding) == candidates.FEATURES
        # warm up torch
        self.model.predict(np.zeros(sign["observation_size"], np.float32), action_masks=np.ones(sign["actions"], bool))
        self.follower: PlanFollower | None = None
        if scenario.campaign.plays_ahead:
            from agents import rollout_plan  # it reads the training objective, whose module reads this one

            self.follower = rollout_plan.PlanFollower(self._plan(path, scenario, encoding))
        elif scenario.campaign.rollout_search == "active":
            _warn_once("campaign.rollout_search: active has nothing to search with campaign.rollouts: 1 (the policy "
                       "decides greedily as the lab goes); set campaign.rollouts too, e.g. 512")

    def _plan(self, path: Path, scenario: Any, encoding: str | None) -> Plan:
        """``campaign.rollouts`` runs of the lab in the twin, the best kept (once per policy and lab: the CLI makes
        a scheduler to check it before the lab makes its own), then ``campaign.local_search``'s swaps on it."""
        from agents.rollout_plan import lab_time, plan

        asked = scenario.campaign.plays_ahead
        off = scenario.campaign.decides_as_it_goes
        if not isinstance(self.encoder, candidates.CandidateEncoder):
            raise PluginError(f"{asked}: {path} reads labs as fixed slots (the earlier kind of policy), and only a "
                              "policy that scores candidates plays a lab ahead: train one with `twin train SCENARIO`, "
                              f"or set {off}")
        why = why_runs_vary(scenario)
        if why:
            raise PluginError(f"{asked} plays the lab ahead in the twin, and {scenario.name!r} would not run as "
                              f"played: {why}. Set {off} to decide as the lab goes")
        key = (str(path.resolve()), path.stat().st_mtime_ns, scenario.model_dump_json())
        if key not in _plans:  # told on stderr: planning a large shop many times takes a while
            def tell(line: str) -> None:
                if tells_progress():  # not in a bench's workers: the command told it once, checking the plugin
                    print(line, file=sys.stderr, flush=True)

            what = scenario.name  # a shop's file would be stale for a shop generated in memory (benches, training)
            if scenario.jobshop is not None:
                what += f" ({scenario.campaign.budget} jobs on {len(scenario.devices)} machines)"
            tell(f"rl: playing {what} {scenario.campaign.rollouts} times in the twin ...")
            rollouts = scenario.campaign.rollouts

            def played(n: int, best_h: float) -> None:
                tell(f"rl: {n} of {rollouts} played, the shortest so far {lab_time(best_h)}")

            def going(share: float, seconds: float) -> None:
                tell(f"rl: {100 * share:.0f} % played, {seconds:.0f} s so far")

            def searching(swaps: int, best_h: float, seconds: float) -> None:
                tell(f"rl: {swaps:,} of {scenario.campaign.local_search:,} swaps tried, the shortest plan so far "
                     f"{lab_time(best_h)}, {seconds:.0f} s so far")

            _plans[key] = plan(scenario, self.model.policy.action_net, rollouts, str(encoding), played,
                               self.encoder.held, going, searching)
            tell(f"rl: {_plans[key].describe()}; the lab follows it")
        return _plans[key]

    @classmethod
    def from_model(cls, model: Any, scenario: Any, encoding: str = "slots") -> RlScheduler:
        """A policy still in training, deciding the same way."""
        self = cls.__new__(cls)
        self.model, self.encoder, self.follower = model, encoder_for(scenario, encoding), None
        return self

    def decide(self, view: LabView) -> list[Assignment]:
        if self.follower is not None:
            planned = self.follower.decide(view)
            if planned is not None:
                return planned
            self.follower = None
        obs, mask = self.encoder.encode(view)
        if isinstance(self.encoder, candidates.CandidateEncoder):
            with torch.no_grad():
                logits = self.model.policy.action_net(torch.as_tensor(obs).unsqueeze(0))[0]
            return self.encoder.decode(view, greedy(logits, mask))
        action, _ = self.model.predict(obs, action_masks=mask, deterministic=True)
        return self.encoder.decode(view, int(action))


def greedy(logits: torch.Tensor, mask: np.ndarray) -> int:
    """The action SB3's ``predict(deterministic=True)`` takes for these scores — the most probable under the
    mask, computed as its masked categorical does (so ties fall the same way) — without its per-call set-up
    (switching every module to eval mode, building distributions), half of a decision's time."""
    masked = torch.where(torch.as_tensor(mask), logits, torch.tensor(-1e8, dtype=logits.dtype))
    return int(torch.softmax(masked - masked.logsumexp(-1, keepdim=True), -1).argmax())
