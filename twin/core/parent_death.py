"""A child process that ends with the process that started it, however that one ends (SIGKILL too): Linux's
PR_SET_PDEATHSIG. The benches' workers ask for it, and so does the Rerun server a lab serves (before it becomes
Rerun's binary: the setting outlives the exec). It is tied to the thread that started the child."""

from __future__ import annotations

import ctypes
import os
import signal

PR_SET_PDEATHSIG = 1


def ends_with_parent(parent: int, sig: int = signal.SIGTERM) -> bool:
    """``sig`` for this process when ``parent`` (its parent's pid, as the parent knew it) ends; False if it has
    ended already (this process then has another parent). Not Linux: left as it was, and True."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, sig)
    except (OSError, AttributeError):
        return True
    return os.getppid() == parent
