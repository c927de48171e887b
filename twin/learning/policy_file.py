"""Reading an SB3 policy file without running code from it.

An SB3 ``.zip`` keeps a few of a model's attributes (its spaces, schedules, policy and buffer classes) as
cloudpickle, and ``PPO.load`` unpickles them: a policy file from someone else could run any code on loading.
Here each of those attributes is unpickled by an unpickler that resolves only what such a file holds — numpy
arrays and dtypes, gymnasium spaces, SB3's schedules, policy and buffer classes, torch activations — and refuses
anything else, naming the file, the attribute and what it asked for; the results go to ``load`` as its
``custom_objects``, so SB3 unpickles nothing itself. Weights are read by SB3 with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import base64
import binascii
import importlib
import io
import json
import pickle
import sys
import zipfile
from pathlib import Path
from typing import Any

from twin.core.errors import PluginError

#: what a policy file may unpack to: this project's are 0.15-0.25 MB; a zip "bomb" of a few kB can unpack to
#: gigabytes, read into memory by the checks below and then by SB3's load
MAX_UNPACKED_BYTES = 512 * 2**20

# what numpy, gymnasium and SB3 themselves pickle, resolved by exact name
_EXACT = {
    ("numpy", "ndarray"), ("numpy._core.numeric", "_frombuffer"), ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.multiarray", "scalar"), ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"), ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.random._pickle", "__generator_ctor"), ("numpy.random._pickle", "__bit_generator_ctor"),
    ("numpy.random._pickle", "__randomstate_ctor"), ("numpy.random._pcg64", "PCG64"),
    ("numpy.random._pcg64", "PCG64DXSM"), ("numpy.random._mt19937", "MT19937"), ("numpy.random._philox", "Philox"),
    ("numpy.random._sfc64", "SFC64"), ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
    ("numpy.random.bit_generator", "SeedSequence"), ("numpy.random._generator", "Generator"),
    ("collections", "deque"), ("collections", "OrderedDict"),
    ("stable_baselines3.common.utils", "FloatSchedule"), ("stable_baselines3.common.utils", "ConstantSchedule"),
    ("stable_baselines3.common.utils", "LinearSchedule"),
}
# modules a class may be imported from to be looked at (importing any other module could itself run code)
_PACKAGES = ("stable_baselines3.", "sb3_contrib.", "gymnasium.spaces.", "torch.nn.modules.activation", "agents.")


class _Refused(pickle.UnpicklingError):
    """What the file asked for and is not given."""


def _dtype(*args: Any) -> Any:
    import numpy as np

    dtype = np.dtype(*args)
    if dtype.hasobject:
        raise _Refused("an array of Python objects")
    return dtype


def _class_allowed(obj: Any) -> bool:
    """A policy, a rollout buffer, a space or an activation: what an SB3 model's pickled attributes name."""
    if not isinstance(obj, type):
        return False
    import torch
    from gymnasium.spaces import Space
    from stable_baselines3.common.buffers import BaseBuffer
    from stable_baselines3.common.policies import BasePolicy

    if issubclass(obj, (BasePolicy, BaseBuffer, Space)):
        return True
    return issubclass(obj, torch.nn.Module) and obj.__module__ == "torch.nn.modules.activation"


class _Unpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("numpy", "dtype"):
            return _dtype
        if (module, name) in _EXACT:
            return super().find_class(module, name)
        if module in sys.modules or module.startswith(_PACKAGES):
            try:
                obj = getattr(importlib.import_module(module), name)
            except (ImportError, AttributeError):
                obj = None
            if _class_allowed(obj):
                return obj
        raise _Refused(f"{module}.{name}")


def safe_objects(path: Path) -> dict[str, Any]:
    """The pickled attributes of the SB3 model at ``path``, unpickled with only what such a file needs: to be
    handed to ``load`` as ``custom_objects``. Raises ``PluginError`` for a file that asks for anything else."""
    try:
        with zipfile.ZipFile(path) as archive:
            unpacked = sum(item.file_size for item in archive.infolist())
            if unpacked > MAX_UNPACKED_BYTES:
                raise PluginError(f"{path}: would unpack to {unpacked / 2**20:,.0f} MB, more than a policy file "
                                  f"does ({MAX_UNPACKED_BYTES / 2**20:,.0f} MB at most; a zip bomb?); nothing was "
                                  "loaded. Use a policy saved by `twin train`")
            data = json.loads(archive.read("data"))
    except (zipfile.BadZipFile, KeyError, OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise PluginError(f"{path}: not an SB3 policy file ({exc}); policies are saved by `twin train`") from exc
    if not isinstance(data, dict):
        raise PluginError(f"{path}: not an SB3 policy file (its data is not an object)")
    objects = {}
    for key, value in data.items():
        if not (isinstance(value, dict) and ":serialized:" in value):
            continue
        try:
            raw = base64.b64decode(str(value[":serialized:"]), validate=True)
            objects[key] = _Unpickler(io.BytesIO(raw)).load()
        except _Refused as exc:
            raise PluginError(f"{path}: its {key!r} asks for {exc}, which a policy file has no need of; labtwin "
                              "does not run code from a policy file. Use a policy saved by `twin train`") from exc
        except (pickle.UnpicklingError, binascii.Error, ValueError, TypeError, EOFError, AttributeError,
                IndexError, KeyError, MemoryError) as exc:
            raise PluginError(f"{path}: its {key!r} cannot be read ({type(exc).__name__}: {exc}); "
                              "the file is damaged: save it again with `twin train`") from exc
    return objects
