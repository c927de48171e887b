"""Stable-Baselines3 models that leave nothing behind: training reports its own progress."""

from __future__ import annotations

from typing import TypeVar

from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.logger import Logger

Model = TypeVar("Model", bound=BaseAlgorithm)


def without_log_dir(model: Model) -> Model:
    """The model with a logger that writes nowhere: SB3's default one makes an empty ``/tmp/SB3-<time>``
    directory at every ``learn()`` call, and training calls it once per evaluation (hundreds per session)."""
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model
