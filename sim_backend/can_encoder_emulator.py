"""Emulated CiA 406 swivel-pulley encoders on a canopen LocalNode (drivers/od/cia406_encoder.eds).

16-bit single-turn position 0x6004, relative to power-on (the encoder reads 0, or the preset 0x6003, at
power-on and wraps at 65536), sent in TPDO1 at every SYNC once the node is operational. The angle comes
from ``plant.swivel_angle()[index]``; an optional Gaussian noise (rad) is added before quantisation.
"""

from __future__ import annotations

import math
from pathlib import Path

import canopen
import numpy as np

from sim_backend.can_drive_emulator import SimulatedNode
from sim_backend.plant import Plant, scalar_reader


class CanEncoderEmulator(SimulatedNode):
    """One swivel encoder reading ``plant.swivel_angle()[index]``."""

    eds_name = "cia406_encoder.eds"

    def __init__(self, network: canopen.Network, node_id: int, plant: Plant, index: int,
                 noise: float = 0.0, rng: np.random.Generator | None = None, eds: str | Path | None = None):
        self.noise = float(noise)  # rad, standard deviation
        self._angle = scalar_reader(plant, "swivel_angle", index)  # rad, absolute
        self._angle0 = self._angle()  # power-on angle, the zero of the counts
        self._preset_offset = 0
        super().__init__(network, node_id, plant, index, rng, eds)
        self.resolution = int(self.node.object_dictionary[0x6001].default)
        self.total_range = int(self.node.object_dictionary[0x6002].default)
        self.operating = int(self.node.object_dictionary[0x6000].default)

    def raw_counts(self) -> int:
        """Counts since power-on before preset and wrap (rounded to the resolution)."""
        angle = self._angle() - self._angle0
        if self.noise:
            angle += self.noise * self.rng.standard_normal()
        c = int(round(angle * self.resolution / (2 * math.pi)))
        return -c if self.operating & 0x01 else c

    def position(self) -> int:
        """0x6004: counts in [0, total measuring range)."""
        return (self.raw_counts() + self._preset_offset) % self.total_range

    def live_getter(self, index: int, subindex: int):
        """0x6004, the position sent at SYNC."""
        return self.position if index == 0x6004 else None

    def process_value(self, index: int, subindex: int):
        if index == 0x6004:
            return self.position()
        if index == 0x6500:
            return self.operating
        if index == 0x6000:
            return self.operating
        if index == 0x6001:
            return self.resolution
        if index == 0x6002:
            return self.total_range
        return None

    def on_object_written(self, index: int, subindex: int, value) -> None:
        with self.lock:
            if index == 0x6003:  # preset: the current position becomes `value`
                self._preset_offset = int(value) - self.raw_counts()
            elif index == 0x6000:
                self.operating = int(value)
            elif index == 0x6001:
                if int(value) <= 0:
                    raise canopen.SdoAbortedError(0x06090030)
                self.resolution = int(value)
            elif index == 0x6002:
                if int(value) <= 0:
                    raise canopen.SdoAbortedError(0x06090030)
                self.total_range = int(value)
