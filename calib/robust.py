"""The median, the very numbers of ``np.median``, without numpy's first-use import of numpy.ma.

``np.median`` checks its result for NaN through ``np.ma.isMaskedArray``, and the first such call imports
numpy.ma (~25 ms): every `cdpr solve` paid it for a few medians of the window search. This one partitions
and averages the middle element(s) as numpy does (the same ``np.partition`` and ``np.mean``), and a column
holding a NaN has a NaN median, as with numpy.
"""

from __future__ import annotations

import numpy as np


def median(a: np.ndarray, axis: int | None = None) -> np.ndarray | float:
    """The median of ``a`` along ``axis`` (None: of every element), same units as ``a``."""
    a = np.asanyarray(a)
    size = a.size if axis is None else a.shape[axis]
    kth = [size // 2 - 1, size // 2] if size % 2 == 0 else [(size - 1) // 2]
    nans = np.issubdtype(a.dtype, np.inexact)
    if nans:
        kth.append(-1)  # a NaN sorts last: the last element tells whether the column holds one
    part = np.partition(a, kth, axis=axis)
    if part.shape == ():
        return part.item()
    axis = 0 if axis is None else axis
    mid = part.shape[axis] // 2
    middle = slice(mid, mid + 1) if part.shape[axis] % 2 == 1 else slice(mid - 1, mid + 1)
    out = np.mean(part[(slice(None),) * axis + (middle,)], axis=axis)
    if nans and size > 0:
        last = part.take(-1, axis=axis)
        has_nan = np.isnan(last)
        if has_nan.any():
            if np.ndim(out) == 0:
                return last
            np.copyto(out, last, where=has_nan)
    return out
