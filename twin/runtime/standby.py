"""A lab that serves with no campaign yet (``twin lab serve`` of a lab file alone): the drivers its devices stand by
with until campaigns come."""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

from twin.campaign.human import DRIVER as HUMAN
from twin.core import plugins
from twin.core.errors import DriverError
from twin.device.driver import feature
from twin.runtime.assembly import load_driver
from twin.scenario import Chemistry, Scenario


def standby_drivers(s: Scenario, skip: Collection[str]) -> list[tuple[str, str, Any]]:
    """A lab that serves with no campaign yet: each device's driver for the lab file's chemistry, or else for the
    first one it simulates (it answers health checks; each campaign submitted brings its own)."""
    out = []
    for dtype, spec in s.devices.items():
        for name in s.instance_names(dtype):
            if name in skip or spec.driver == HUMAN:
                continue
            try:
                out.append((name, dtype, load_driver(s, dtype, name)))
            except DriverError:
                models = feature(plugins.load("devices", spec.driver), "chemistry_models")
                if not models:
                    raise
                alt = s.model_copy(update={"chemistry": Chemistry(model=sorted(models)[0])})
                out.append((name, dtype, load_driver(alt, dtype, name)))
    return out
