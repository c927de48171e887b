"""Random streams keyed by what they are for, so a draw never depends on what was drawn before."""

from __future__ import annotations

import hashlib
import random

import numpy as np


def seeded(seed: int, *names: str) -> tuple[random.Random, np.random.Generator]:
    """Independent, reproducible streams per (seed, names)."""
    key = ":".join([str(seed), *names])
    r = random.Random(key)
    return r, np.random.default_rng(r.getrandbits(64))


def keyed_uniforms(key: str) -> tuple[float, float]:
    """Two uniform draws in [0, 1) that depend on ``key`` alone (a hash, ~20× cheaper than seeding a
    ``random.Random``): for draws that must not depend on what was drawn before."""
    digest = hashlib.blake2b(key.encode(), digest_size=16).digest()
    return (int.from_bytes(digest[:8], "little") >> 11) * 2.0**-53, (int.from_bytes(digest[8:], "little") >> 11) * 2.0**-53
