"""Open the devices a device file describes (:class:`drivers.config.DeviceConfig`): the one place that does it.

:func:`open_devices` opens the CAN bus and its :class:`drivers.can_bus.CanNetwork`, makes the SYNC producer, one
driver per winch drive and swivel encoder (cable order) and the serial drivers (load-cell amplifier, AHRS), and
hands them over as one :class:`DeviceSet`. The acquisition (``cdpr startup``), ``cdpr devices check``, the
simulator's tests and benchmarks all come through here, the simulated prototype's device set included.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import can

from drivers.can_bus import CanNetwork, SyncProducer, open_bus_from_config, open_network
from drivers.canopen_drive import CanopenWinchDrive
from drivers.config import DeviceConfig, DeviceConfigError
from drivers.interfaces import DeviceError
from drivers.loadcell import LoadCellConfig, LoadCellDriver
from drivers.swivel_encoder import CanopenSwivelEncoder
from drivers.xsens import XsensConfig, XsensMti, config_problem


@dataclass
class DeviceSet:
    """The drivers of one device file, not yet opened (:meth:`open` or :meth:`open_each`); close it to stop the
    nodes, release the ports and the bus. ``loadcells`` and ``ahrs`` are None when the file has none."""

    network: CanNetwork
    sync: SyncProducer
    drives: list[CanopenWinchDrive] = field(default_factory=list)
    encoders: list[CanopenSwivelEncoder] = field(default_factory=list)
    loadcells: LoadCellDriver | None = None
    ahrs: XsensMti | None = None

    @property
    def devices(self) -> list:
        """Every driver: drives, encoders (cable order), then the load cells and the AHRS when present."""
        return [*self.drives, *self.encoders, *(d for d in (self.loadcells, self.ahrs) if d is not None)]

    def open(self) -> None:
        """Open every device in order; the first that fails closes the whole set and raises its DeviceError."""
        try:
            for dev in self.devices:
                dev.open()
        except BaseException:
            self.close()
            raise

    def open_each(self) -> dict:
        """Open every device that can be: {device: the DeviceError sentence} of those that cannot."""
        failed = {}
        for dev in self.devices:
            try:
                dev.open()
            except DeviceError as exc:
                failed[dev] = str(exc)
        return failed

    def send_sync(self) -> int:
        """Send one SYNC; its unwrapped counter."""
        return self.sync.send_sync()

    def wait_for_sync(self, count: int, timeout: float = 1.0) -> tuple[list, list]:
        """Readings of every drive and encoder answering SYNC ``count`` (DeviceError on timeout)."""
        return ([d.wait_for_sync(count, timeout) for d in self.drives],
                [e.wait_for_sync(count, timeout) for e in self.encoders])

    def faults(self) -> dict[str, str | None]:
        """The pending fault of every device by name (None when fine)."""
        return {d.name: d.fault() for d in self.devices}

    def close(self) -> None:
        """Close every device (last opened first), then the network and its bus; safe to call twice."""
        for dev in reversed(self.devices):
            try:
                dev.close()
            except Exception:  # closing what may already be gone
                pass
        if self.network.bus is not None:
            self.network.disconnect()

    def __enter__(self) -> DeviceSet:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_devices(config: DeviceConfig, length_per_motor_rev: Sequence[float], swivel_counts_per_rev: int = 65536,
                 clock: Callable[[], float] = time.monotonic, every: tuple[int, int] = (1, 1),
                 control_period: float = 0.005, polled: bool = False, stale_periods: float = 3.0,
                 open_now: bool = True, bus: can.BusABC | None = None, listener: can.Listener | None = None,
                 serial_tap: Callable[[str], Callable | None] | None = None) -> DeviceSet:
    """The drivers of every device of ``config`` on a freshly opened bus, opened at once with ``open_now``.

    ``length_per_motor_rev``: m of cable per motor revolution, one per drive (the robot description's
    ``sensors.length_per_motor_rev``); ``clock``: the CAN drivers' time stamps and heartbeat checks (the loop's
    clock); ``every``: the drives and the encoders send their readings every n-th SYNC; ``control_period``: s,
    the load cells' expected sample period; ``polled`` and ``stale_periods``: the serial drivers read their ports
    in the waiting thread, and call a reading stale after that many periods. ``bus``: a python-can bus to use
    instead of the one the file names (a replay's); ``listener``: gets every CAN frame received and sent from
    the first on (:meth:`CanNetwork.add_listener`, a raw record); ``serial_tap(name)``: the tap of the serial
    device ``name`` ("loadcells", "ahrs") that gets its bytes both ways. DeviceError (one sentence) when the
    bus or a device does not answer, DeviceConfigError when the file asks for what a driver cannot do.
    """
    if len(length_per_motor_rev) < len(config.drives):
        raise DeviceConfigError(f"{config.source}: {len(config.drives)} drives but only {len(length_per_motor_rev)} "
                                f"transmission ratios in the robot description")
    ahrs = None
    if config.ahrs is not None:
        ahrs_config = XsensConfig(config.ahrs.port, config.ahrs.baud, rate_hz=int(config.ahrs.rate),
                                  ack_timeout=config.answer_timeout, stale_periods=stale_periods, polled=polled,
                                  tap=serial_tap and serial_tap("ahrs"))
        problem = config_problem(ahrs_config)
        if problem:
            raise DeviceConfigError(f"{config.source}: field 'ahrs.rate' = {config.ahrs.rate}: {problem}")
        ahrs = XsensMti(ahrs_config)
    loadcells = None
    if config.loadcells is not None:
        loadcells = LoadCellDriver(LoadCellConfig(config.loadcells.port, config.loadcells.baud,
                                                  channels=len(config.drives), rate_hz=1.0 / control_period,
                                                  info_timeout=config.answer_timeout,
                                                  stale_periods=stale_periods, polled=polled,
                                                  tap=serial_tap and serial_tap("loadcells")))
    bus = open_bus_from_config(config.can) if bus is None else bus
    try:
        network = open_network(bus)
        if listener is not None:
            network.add_listener(listener)
    except BaseException:
        bus.shutdown()
        raise
    sync = SyncProducer(network, config.can.sync_overflow)
    hb = config.can.heartbeat_period
    devices = DeviceSet(network, sync, loadcells=loadcells, ahrs=ahrs)
    try:
        devices.drives = [CanopenWinchDrive(network, n.node_id, sync, float(length_per_motor_rev[i]), name=n.name,
                                            clock=clock, heartbeat_period=hb, every=every[0])
                          for i, n in enumerate(config.drives)]
        devices.encoders = [CanopenSwivelEncoder(network, n.node_id, sync, name=n.name, clock=clock,
                                                 heartbeat_period=hb, counts_per_rev=swivel_counts_per_rev,
                                                 every=every[1])
                            for n in config.encoders]
        if open_now:
            devices.open()
    except BaseException:
        devices.close()
        raise
    return devices
