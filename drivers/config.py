"""The device set of a robot: CAN bus and node ids, serial ports, rates (a YAML file).

Example (``drivers/examples/irma4u_devices.yaml``)::

    can:
      interface: socketcan     # python-can interface name (the simulated prototype's: cdpr_sim)
      channel: can0
      bitrate: 1000000         # bit/s
      heartbeat_period: 0.1    # s, producer heartbeat time written to every node (0x1017)
      sync_overflow: 240       # SYNC counter overflow (0x1019), 0 for SYNC frames without counter
    drives:                    # CiA 402 winch drives, one per cable, in cable order
      - {name: winch1, node_id: 1}
    encoders:                  # CiA 406 swivel encoders, one per cable, in cable order
      - {name: swivel1, node_id: 11}
    loadcells: {port: /dev/ttyUSB0, baud: 115200}
    ahrs: {port: /dev/ttyUSB1, baud: 115200, rate: 100}

Every error names the file, the field and the value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import can.interfaces
import yaml

from calib.errors import CdprError
from calib.fields import FieldReader, read_yaml

CAN_BITRATES = (10_000, 20_000, 50_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


class DeviceConfigError(CdprError, ValueError):
    """A device configuration that cannot be used; the message names the file, field and value."""


@dataclass(frozen=True)
class CanConfig:
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 1_000_000  # bit/s
    heartbeat_period: float = 0.1  # s, 0x1017 written to every node; 0 disables heartbeat monitoring
    sync_overflow: int = 240  # 0x1019

    @property
    def heartbeat_ms(self) -> int:
        return int(round(self.heartbeat_period * 1000.0))


@dataclass(frozen=True)
class NodeConfig:
    name: str
    node_id: int  # 1..127


@dataclass(frozen=True)
class SerialConfig:
    port: str
    baud: int = 115200


@dataclass(frozen=True)
class AhrsConfig:
    port: str
    baud: int = 115200
    rate: float = 100.0  # Hz, output data rate requested from the AHRS


@dataclass(frozen=True)
class DeviceConfig:
    can: CanConfig = field(default_factory=CanConfig)
    drives: tuple[NodeConfig, ...] = ()
    encoders: tuple[NodeConfig, ...] = ()
    loadcells: SerialConfig | None = None
    ahrs: AhrsConfig | None = None
    source: str = "<config>"  # the file it came from, for messages
    # s a serial device's handshake answer (load-cell INFO, AHRS acknowledgement) is awaited: the real devices' 1 s;
    # not a file field. The simulated prototype sets its plant's guard (its devices answer from a process that a
    # loaded machine may run late, so a wall-time second there is a race, not a check)
    answer_timeout: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "can": {"interface": self.can.interface, "channel": self.can.channel, "bitrate": self.can.bitrate,
                    "heartbeat_period": self.can.heartbeat_period, "sync_overflow": self.can.sync_overflow},
            "drives": [{"name": n.name, "node_id": n.node_id} for n in self.drives],
            "encoders": [{"name": n.name, "node_id": n.node_id} for n in self.encoders],
        }
        if self.loadcells is not None:
            d["loadcells"] = {"port": self.loadcells.port, "baud": self.loadcells.baud}
        if self.ahrs is not None:
            d["ahrs"] = {"port": self.ahrs.port, "baud": self.ahrs.baud, "rate": self.ahrs.rate}
        return d

    def check_robot(self, n_cables: int) -> None:
        """Raise DeviceConfigError unless there is one drive and one encoder per cable."""
        for key, nodes in (("drives", self.drives), ("encoders", self.encoders)):
            if len(nodes) != n_cables:
                raise DeviceConfigError(
                    f"{self.source}: field '{key}' lists {len(nodes)} nodes but the robot has {n_cables} cables")


class _Fields(FieldReader):
    """Typed access to a device file's fields (calib/fields.py); its sentences end without a period."""

    error = DeviceConfigError
    end = ""

    def mapping(self, value: Any, fld: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(fld, value, "must be a mapping")
        return value

    def unknown(self, m: dict, fld: str, allowed: tuple[str, ...]) -> None:
        for key in m:
            if key not in allowed:
                prefix = f"{fld}." if fld else ""
                raise self.fail(f"{prefix}{key}", m[key], f"is not a known field (known: {', '.join(allowed)})")

    def integer(self, value: Any, fld: str, lo: int | None = None, hi: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(fld, value, "must be an integer")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise self.fail(fld, value, f"must be in [{lo}, {hi}]")
        return value

    def number(self, value: Any, fld: str, lo: float = 0.0, hi: float | None = None, strict: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.fail(fld, value, "must be a number")
        v = float(value)
        if v != v or (strict and v <= lo) or v < lo or (hi is not None and v > hi):
            bound = f"> {lo}" if strict else f">= {lo}"
            raise self.fail(fld, value, f"must be {bound}" + (f" and <= {hi}" if hi is not None else ""))
        return v

    def text(self, value: Any, fld: str) -> str:
        if not isinstance(value, str) or not value.strip():
            raise self.fail(fld, value, "must be a non-empty string")
        return value


def device_config_from_dict(data: Any, source: str = "<config>") -> DeviceConfig:
    """Validate a parsed YAML mapping into a :class:`DeviceConfig`."""
    f = _Fields(source)
    if not isinstance(data, dict):
        raise DeviceConfigError(f"{source}: the file must hold a mapping with 'can', 'drives', 'encoders', "
                                f"got {type(data).__name__}")
    f.unknown(data, "", ("can", "drives", "encoders", "loadcells", "ahrs"))
    c = f.mapping(data.get("can", {}), "can")
    f.unknown(c, "can", ("interface", "channel", "bitrate", "heartbeat_period", "sync_overflow"))
    interface = f.text(c.get("interface", "socketcan"), "can.interface")
    if interface not in can.interfaces.VALID_INTERFACES:  # python-can's own and the installed plugins
        raise f.fail("can.interface", interface, f"is not a python-can interface "
                                                  f"({', '.join(sorted(can.interfaces.VALID_INTERFACES))})")
    channel = c.get("channel", "can0")
    if isinstance(channel, int) and not isinstance(channel, bool):
        channel = str(channel)
    channel = f.text(channel, "can.channel")
    bitrate = f.integer(c.get("bitrate", 1_000_000), "can.bitrate")
    if bitrate not in CAN_BITRATES:
        raise f.fail("can.bitrate", bitrate, f"is not a CiA 301 bit rate ({', '.join(map(str, CAN_BITRATES))})")
    hb = f.number(c.get("heartbeat_period", 0.1), "can.heartbeat_period", 0.0, 65.535)
    if hb and hb < 0.001:
        raise f.fail("can.heartbeat_period", hb, "must be 0 (off) or at least 0.001 s")
    overflow = f.integer(c.get("sync_overflow", 240), "can.sync_overflow", 0, 240)
    if overflow == 1:
        raise f.fail("can.sync_overflow", overflow, "must be 0 or 2..240")
    can_cfg = CanConfig(interface, channel, bitrate, hb, overflow)

    seen: dict[int, str] = {}
    groups = {}
    for key in ("drives", "encoders"):
        items = data.get(key, [])
        if not isinstance(items, list):
            raise f.fail(key, items, "must be a list of {name, node_id}")
        nodes = []
        for k, item in enumerate(items):
            fld = f"{key}[{k}]"
            m = f.mapping(item, fld)
            f.unknown(m, fld, ("name", "node_id"))
            if "node_id" not in m:
                raise f.fail(f"{fld}.node_id", None, "is missing")
            nid = f.integer(m["node_id"], f"{fld}.node_id", 1, 127)
            name = f.text(m.get("name", f"{key[:-1]}{k + 1}"), f"{fld}.name")
            if nid in seen:
                raise f.fail(f"{fld}.node_id", nid, f"is already used by {seen[nid]}")
            seen[nid] = fld
            nodes.append(NodeConfig(name, nid))
        groups[key] = tuple(nodes)

    loadcells = None
    if data.get("loadcells") is not None:
        m = f.mapping(data["loadcells"], "loadcells")
        f.unknown(m, "loadcells", ("port", "baud"))
        loadcells = SerialConfig(f.text(m.get("port"), "loadcells.port"),
                                 f.integer(m.get("baud", 115200), "loadcells.baud", 300, 12_000_000))
    ahrs = None
    if data.get("ahrs") is not None:
        m = f.mapping(data["ahrs"], "ahrs")
        f.unknown(m, "ahrs", ("port", "baud", "rate"))
        ahrs = AhrsConfig(f.text(m.get("port"), "ahrs.port"),
                          f.integer(m.get("baud", 115200), "ahrs.baud", 300, 12_000_000),
                          f.number(m.get("rate", 100.0), "ahrs.rate", 0.0, 2000.0, strict=True))
    return DeviceConfig(can_cfg, groups["drives"], groups["encoders"], loadcells, ahrs, source)


def load_device_config(path: str | Path) -> DeviceConfig:
    """Read and validate a device YAML file."""
    p = Path(path)
    return device_config_from_dict(read_yaml(p, DeviceConfigError, "device configuration", end=""), str(p))


def dump_device_config(config: DeviceConfig, path: str | Path) -> None:
    """Write ``config`` as YAML (readable back by :func:`load_device_config`)."""
    Path(path).write_text(yaml.safe_dump(config.to_dict(), sort_keys=False))


def example_config_path(name: str = "irma4u_devices.yaml") -> Path:
    """Path of an example device file installed with the package."""
    return Path(str(resources.files("drivers") / "examples" / name))


def eds_path(name: str) -> Path:
    """Path of an installed EDS file: 'cia402_winch.eds' or 'cia406_encoder.eds'."""
    return Path(str(resources.files("drivers") / "od" / name))
