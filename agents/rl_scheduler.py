"""`rl`: a MaskablePPO policy (`twin train SCENARIO`) deciding which ready step runs on which free device.

``serve_on_bus`` makes the lab run it as an agent on the bus (``twin.runtime.remote_scheduler``):
the orchestrator asks it over Zenoh, with a deadline and the scenario's fallback rule.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.scheduling_features import ACTIONS, OBS_SIZE, Encoder, signature
from twin import Assignment, LabView
from twin import PluginError
from twin import load_policy


class RlScheduler:
    serve_on_bus = True

    def __init__(self, scenario: Any = None, policy: str | None = None, **_: Any) -> None:
        if not policy or scenario is None:
            raise PluginError("the rl scheduler needs a trained policy: train one with "
                              "`twin train SCENARIO --out P.zip`, then use --scheduler rl:P.zip")
        torch.set_num_threads(1)
        self.model = load_policy(Path(policy), "scheduler", signature(scenario))
        self.encoder = Encoder(scenario)
        self.model.predict(np.zeros(OBS_SIZE, np.float32), action_masks=np.ones(ACTIONS, bool))  # warm up torch

    @classmethod
    def from_model(cls, model: Any, scenario: Any) -> RlScheduler:
        """A policy still in training, deciding the same way."""
        self = cls.__new__(cls)
        self.model, self.encoder = model, Encoder(scenario)
        return self

    def decide(self, view: LabView) -> list[Assignment]:
        obs, mask = self.encoder.encode(view)
        action, _ = self.model.predict(obs, action_masks=mask, deterministic=True)
        return self.encoder.decode(view, int(action))
