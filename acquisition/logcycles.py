"""The logging cycles of a controller's raw text log: its lines grouped by time stamp, under the damage policy.

The IRMA controller writes, every 0.1 s, one line per cable and one AHRS line, each with its own time stamp
printed with 6 significant digits (every stamp of the three real logs: 0.1 ms below 100 s, 1 ms from 100 to
1000 s). The lines of one cycle are stamped up to 0.1 ms apart (measured in sc_8_medium_a: 40 of its 58
cycles below 100 s, the cable lines before the AHRS line), which the 1 ms printing turns into stamps 0 or
1 ms apart (714 of its 2076 cycles past 100 s). So lines belong to one cycle when, sorted by time, each lies
within :func:`cycle_tolerance` of the previous one: one unit of the printed stamp plus ``CYCLE_JITTER``
(1 ms, ten times the spread measured), 1.1-2 ms below 1000 s, far below the period. A cycle takes the time
of its AHRS line (the latest of its stamps, and the time the authors' parser gives the same sample).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from acquisition.damage import CONFLICT, ORDER, REPEATED, DamageLog

PARTIAL = "logging cycles lacking a cable or AHRS line"
STAMP_DIGITS = 6  # significant digits of the printed time stamps
CYCLE_JITTER = 1e-3  # s, allowed spread of one cycle's stamps beyond their printed resolution


def stamp_resolution(t: np.ndarray) -> np.ndarray:
    """One unit of the last printed digit of time stamps ``t`` (s) printed with ``STAMP_DIGITS`` significant
    digits (stamps below 1 s count as 1 s)."""
    return 10.0 ** (np.floor(np.log10(np.maximum(np.abs(t), 1.0))) - (STAMP_DIGITS - 1))


def cycle_tolerance(t: np.ndarray) -> np.ndarray:
    """Largest gap (s) between two time-sorted stamps of one logging cycle near times ``t`` (s)."""
    return stamp_resolution(t) + CYCLE_JITTER


@dataclass
class LogCycles:
    """The complete logging cycles of a log, in time order.

    ``rows`` (cycles, keys): the record of each key (cable 0..3, then the AHRS) in each cycle; ``t`` (cycles,) s:
    the stamp of the cycle's last key (the AHRS line); ``first_line`` (cycles,): its first line in the file.
    """

    rows: np.ndarray
    t: np.ndarray
    first_line: np.ndarray


def group_cycles(t: np.ndarray, key: np.ndarray, line: np.ndarray, values: np.ndarray, keys: int,
                 damage: DamageLog) -> LogCycles:
    """Group a log's valid records into logging cycles and keep the complete ones.

    ``t`` (n,) stamps, s; ``key`` (n,) 0..keys-1, what each record reads (each cycle needs every key once);
    ``line`` (n,) its line number; ``values`` (n, m) its readings. Counted in ``damage``: a key repeated in a
    cycle with the same readings (kept once), a cycle with a key twice with other readings (skipped whole), a
    cycle lacking a key (skipped: nothing is invented), complete cycles out of file order (put back in place).
    """
    n = t.size
    if n == 0:
        return LogCycles(np.zeros((0, keys), dtype=int), np.zeros(0), np.zeros(0, dtype=int))
    order = np.argsort(t, kind="stable")
    ts = t[order]
    cyc = np.empty(n, dtype=int)
    cyc[order] = np.cumsum(np.r_[False, np.diff(ts) > cycle_tolerance(ts[1:])])
    cycles = int(cyc.max()) + 1
    first = np.full(cycles, np.iinfo(np.int64).max)
    np.minimum.at(first, cyc, line)
    o = np.lexsort((line, key, cyc))  # by cycle, then key, then line: each key's first line leads its group
    head = np.r_[True, (cyc[o][1:] != cyc[o][:-1]) | (key[o][1:] != key[o][:-1])]
    lead = o[np.maximum.accumulate(np.where(head, np.arange(n), 0))]  # the first line of each record's group
    dup = ~head
    same = np.all(values[o[dup]] == values[lead[dup]], axis=1)
    repeated = o[dup][same]
    if repeated.size:
        damage.add(REPEATED, f"first: line {int(line[repeated].min())}", repeated.size)
    conflict = np.zeros(cycles, dtype=bool)
    conflict[cyc[o[dup][~same]]] = True
    if conflict.any():
        damage.add(CONFLICT, f"first: the cycle at line {int(first[conflict].min())}", int(conflict.sum()))
    rows = np.full((cycles, keys), -1)
    rows[cyc[o[head]], key[o[head]]] = o[head]
    complete = (rows >= 0).all(axis=1) & ~conflict
    partial = np.flatnonzero(~complete & ~conflict)
    if partial.size:
        damage.add(PARTIAL, f"first: the cycle at line {int(first[partial[0]])}", partial.size)
    appearance = first[complete]
    late = np.flatnonzero(appearance[1:] < np.maximum.accumulate(appearance)[:-1]) + 1
    if late.size:
        damage.add(ORDER, f"first: the cycle at line {int(appearance[late[0]])}", late.size)
    rows = rows[complete]
    return LogCycles(rows, t[rows[:, -1]], appearance)
