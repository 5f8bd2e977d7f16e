"""Parsers of option values shared by several commands; bad values raise UsageError (exit 2)."""

from __future__ import annotations

import math

import numpy as np

from acquisition.cli.errors import UsageError


def parse_pose(text: str | None, option: str = "--reference") -> np.ndarray | None:
    """A pose x,y,z,roll,pitch,yaw (m, rad) from a comma-separated option value, or None."""
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6 or not all(math.isfinite(v) for v in vals):
        raise UsageError(f"{option} '{text}' must be six numbers x,y,z,roll,pitch,yaw (m, rad).")
    return np.array(vals)
