"""codac, imported with the floating-point rounding mode it needs confined to the interval computations.

Importing codac 2.1.2 switches the whole process to upward rounding (its interval arithmetic relies on it),
which silently changes every later floating-point result of numpy and Python (1/3 becomes
0.33333333333333337) and breaks libraries that check their constants at import (hypothesis). It also sets
the x87 unit to 53-bit precision (control word 0x037f -> 0x0a7f), which round-to-nearest alone does not undo
and which changes what glibc's libm returns in its last bits (enough, before the planner's costs were made
integral, to pick another of several equally cheap pose tours, and so to change every later figure of a
process that had imported codac first). This module saves the whole floating-point
environment (fegetenv: x87 control word and SSE MXCSR), imports codac, keeps codac's environment, restores
the saved one, and offers :func:`codac_rounding`, a context in which codac's environment is active; every
codac computation of the package runs inside it. Without it codac's intervals are not outward-rounded
(1/3 collapses to a point).
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
_ENV_BYTES = 64  # >= sizeof(fenv_t) on every glibc platform (28-32 bytes on x86, 8 on aarch64)


def _get_env() -> ctypes.Array:
    env = ctypes.create_string_buffer(_ENV_BYTES)
    _libm.fegetenv(env)
    return env


_BEFORE = _get_env()

import codac  # noqa: E402  (the environment is read right after the import)

CODAC_MODE = _libm.fegetround()
if CODAC_MODE == _FE_TONEAREST:  # codac imported earlier and the mode since reset: use the platform's upward
    CODAC_MODE = _FE_UPWARD.get(platform.machine(), 0x800)
    _libm.fesetround(CODAC_MODE)
_CODAC_ENV = _get_env()
_libm.fesetenv(_BEFORE)
_libm.fesetround(_FE_TONEAREST)  # (should codac have been imported earlier, under another module's care)


@contextlib.contextmanager
def codac_rounding() -> Iterator[None]:
    """Run the enclosed codac computations in codac's floating-point environment (upward rounding, x87
    53-bit precision), then restore the previous environment."""
    previous = _get_env()
    _libm.fesetenv(_CODAC_ENV)
    try:
        yield
    finally:
        _libm.fesetenv(previous)


__all__ = ["CODAC_MODE", "codac", "codac_rounding"]
