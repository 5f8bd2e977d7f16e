"""CiA 406 swivel-pulley encoder driver over CANopen (EDS drivers/od/cia406_encoder.eds).

Setup by SDO: NMT pre-operational, device type check, resolution check (0x6001/0x6002 against the robot's
counts per revolution), heartbeat 0x1017, TPDO1 = position value 0x6004 at every SYNC or at every n-th one
(from the SYNC with counter 1, CiA 301 SYNC start value), NMT start. Each TPDO
becomes a :class:`SwivelReading` with the counter of the SYNC it answered; the 16-bit counts are unwrapped
into the swivel-angle change since power-on (first reading taken within half a turn of power-on).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import canopen

from drivers.can_bus import SyncProducer
from drivers.canopen_node import CanopenNodeDriver, wrap_delta
from drivers.interfaces import DeviceError, SwivelEncoder, SwivelReading


class CanopenSwivelEncoder(CanopenNodeDriver, SwivelEncoder):
    """One swivel encoder: counts -> rad with ``counts_per_rev`` (65536 for 16 bits); its position comes every
    ``every``-th SYNC (1: all)."""

    profile = 406
    eds_name = "cia406_encoder.eds"

    def __init__(self, network: canopen.Network, node_id: int, sync: SyncProducer, name: str | None = None,
                 clock: Callable[[], float] = time.monotonic, heartbeat_period: float = 0.1,
                 counts_per_rev: int = 65536, eds: str | Path | None = None, every: int = 1):
        super().__init__(network, node_id, sync, name or f"swivel encoder {node_id}", clock, heartbeat_period,
                         eds=eds, every=every)
        self.counts_per_rev = int(counts_per_rev)
        self.bits = self.counts_per_rev.bit_length() - 1
        if 1 << self.bits != self.counts_per_rev:
            raise ValueError(f"{self.name}: counts per revolution must be a power of two, got {counts_per_rev}")
        self._last_raw: int | None = None
        self._unwrapped = 0

    def open(self) -> None:
        try:
            self._open_node()
            units = self.sdo_read(0x6001)
            total = self.sdo_read(0x6002)
            if units != self.counts_per_rev or total != self.counts_per_rev:
                raise DeviceError(f"{self.name} (CAN node {self.node_id}) reports {units} counts per revolution "
                                  f"(0x6001) and a range of {total} (0x6002), expected {self.counts_per_rev}")
            self._map_tpdo(1, [(0x6004, 32)], every=self.every)
            self._disable_pdo(0x1801, 0x180, 2)
            self._start()
        except Exception:
            self.close()
            raise

    def _make_reading(self, t, seq, sync_count, values):
        raw = values[0x6004] % self.counts_per_rev
        if self._last_raw is None:
            self._unwrapped = wrap_delta(raw, 0, self.bits)
        else:
            self._unwrapped += wrap_delta(raw, self._last_raw, self.bits)
        self._last_raw = raw
        return SwivelReading(t=t, seq=seq, counts=raw,
                             delta_angle=self._unwrapped * 2 * math.pi / self.counts_per_rev,
                             sync_count=sync_count)

    def fault(self) -> str | None:
        return self._link_fault()

    def status(self) -> str:
        if self.node is None:
            return f"{self.name}: CAN node {self.node_id}, closed"
        r = self._latest
        if r is None:
            try:
                feedback = f"position {self.sdo_read(0x6004)} counts (SDO), no PDO yet"
            except DeviceError:
                feedback = "no SDO answer"
        else:
            feedback = f"position {r.counts} counts ({math.degrees(r.delta_angle):+.3f} deg), SYNC {r.sync_count}"
        fault = self.fault()
        return (f"{self.name}: CAN node {self.node_id}, NMT {self.nmt_state()}, {feedback}"
                + (f"; FAULT: {fault}" if fault else ""))
