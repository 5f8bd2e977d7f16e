"""codac, imported with the floating-point rounding mode it needs confined to the interval computations.

Importing codac 2.1.2 switches the whole process to upward rounding (its interval arithmetic relies on it),
which silently changes every later floating-point result of numpy and Python (1/3 becomes
0.33333333333333337) and breaks libraries that check their constants at import (hypothesis). This module
imports codac, puts the process back to round-to-nearest, and offers :func:`codac_rounding`, a context in
which codac's mode is active; every codac computation of the package runs inside it. Without it codac's
intervals are not outward-rounded (1/3 collapses to a point).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import platform
from collections.abc import Iterator

_libm = ctypes.CDLL(ctypes.util.find_library("m"))
_FE_TONEAREST = 0
_FE_UPWARD = {"x86_64": 0x800, "AMD64": 0x800, "i686": 0x800, "aarch64": 0x400000, "arm64": 0x400000}

import codac  # noqa: E402  (the rounding mode is read right after the import)

CODAC_MODE = _libm.fegetround()
if CODAC_MODE == _FE_TONEAREST:  # codac imported earlier and the mode since reset: use the platform's upward
    CODAC_MODE = _FE_UPWARD.get(platform.machine(), 0x800)
_libm.fesetround(_FE_TONEAREST)


@contextlib.contextmanager
def codac_rounding() -> Iterator[None]:
    """Run the enclosed codac computations in codac's rounding mode, then restore the previous mode."""
    previous = _libm.fegetround()
    _libm.fesetround(CODAC_MODE)
    try:
        yield
    finally:
        _libm.fesetround(previous)


__all__ = ["CODAC_MODE", "codac", "codac_rounding"]
