"""Operating-system names for Python threads, so `top -H`, `ps -L` and profilers show them.

Python 3.11 gives every thread the process's name at the OS level; on a companion computer that
makes `top -H` useless for asking which thread burns the CPU. Linux keeps a 15-byte name per
thread (``/proc/<pid>/task/<tid>/comm``), set with ``prctl(PR_SET_NAME)``. The benchmarks read
per-thread CPU by these names.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys

log = logging.getLogger(__name__)

_PR_SET_NAME = 15
_NAME_MAX_BYTES = 15

_prctl = None
if sys.platform.startswith("linux"):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        _prctl = _libc.prctl
    except (OSError, AttributeError):  # pragma: no cover - musl without prctl, odd builds
        _prctl = None


def set_native_name(name: str) -> bool:
    """Name the calling thread for the OS (first 15 bytes); False where the OS has no such name."""
    if _prctl is None:
        return False
    raw = name.encode("utf-8", errors="replace")[:_NAME_MAX_BYTES]
    return bool(_prctl(_PR_SET_NAME, ctypes.c_char_p(raw), 0, 0, 0) == 0)
