"""Damaged input: the lines (or samples) a reader or an importer skips or repairs, counted per reason and told
in one warning per file (the policy of docs/run-format.md, shared by :func:`acquisition.runlog.read_run` and
the importers)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


class DamagedInputWarning(UserWarning):
    """A reader or importer skipped damaged lines (or samples) of a file: one warning per file, counting them."""


# Why a line or sample is skipped (or repaired): the same words for every format (docs/run-format.md).
CUT = "cut short (the log was cut while writing it)"
FIELDS = "wrong number of fields"
VALUE = "a non-numeric or non-finite value"
FOREIGN = "not a record of the format"
REPEATED = "repeated (same time, same values; kept once)"
CONFLICT = "same time as another line with other values"
ORDER = "out of time order (put back in place, nothing skipped)"


@dataclass
class DamageLog:
    """What a reader skipped in one file, by reason, with the first place each reason was met.

    ``unit`` names what is counted ("line", "sample", "cycle"). :meth:`warn` issues the one
    :class:`DamagedInputWarning` line; :meth:`summary` is the same text for an error sentence.
    """

    file: Path
    counts: dict[str, int] = field(default_factory=dict)
    first: dict[str, str] = field(default_factory=dict)

    def add(self, reason: str, where: str, count: int = 1) -> None:
        """Count ``count`` damaged items for ``reason``; ``where`` says where the first was (e.g. "line 57")."""
        if count <= 0:
            return
        self.counts[reason] = self.counts.get(reason, 0) + count
        self.first.setdefault(reason, where)

    def __bool__(self) -> bool:
        return bool(self.counts)

    def summary(self) -> str:
        """'2 wrong number of fields (first: line 31 has 25 values), 1 repeated (...) (line 9)'."""
        return ", ".join(f"{c} {r} ({self.first[r]})" for r, c in self.counts.items())

    def warn(self, kept: int, stacklevel: int = 3) -> None:
        """One warning line naming the file, what was skipped and why, and how many samples were kept."""
        if self:
            warnings.warn(f"{self.file}: damaged input: {self.summary()}; {kept} samples kept.",
                          DamagedInputWarning, stacklevel=stacklevel)


def time_order(t: np.ndarray, values: np.ndarray, places: Sequence[str], damage: DamageLog) -> np.ndarray:
    """Indices of the samples to keep, in time order, under the damage policy: samples out of order are put
    back in place; a sample repeated with the same values is kept once; samples that share a time with other
    values are all skipped (which one is right cannot be told). ``values`` (N, m) finite, ``places`` (N,)
    names each sample for the message."""
    N = t.shape[0]
    if N == 0:
        return np.zeros(0, dtype=int)
    late = np.flatnonzero(t[1:] < np.maximum.accumulate(t)[:-1]) + 1
    if late.size:
        damage.add(ORDER, places[int(late[0])], late.size)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    keep = np.ones(N, dtype=bool)
    repeats = np.flatnonzero(ts[1:] == ts[:-1]) + 1
    firsts = np.searchsorted(ts, ts[repeats], side="left")  # sorted: ts and the repeats are
    # each group of equal times once (np.unique would do, but its first call imports numpy.ma: ~25 ms a command)
    for start in firsts[np.r_[True, firsts[1:] != firsts[:-1]]] if firsts.size else firsts:
        end = int(np.searchsorted(ts, ts[start], side="right"))
        group = order[start:end]
        if np.all(values[group] == values[group[0]]):
            keep[start + 1 : end] = False
            damage.add(REPEATED, places[int(group[1])], group.size - 1)
        else:
            keep[start:end] = False
            damage.add(CONFLICT, places[int(group[0])], group.size)
    return order[keep]
