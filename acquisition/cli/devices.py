"""`cdpr devices ...`: read one serial device, check the whole device set."""

from __future__ import annotations

import importlib


def register(sub) -> None:
    parser = sub.add_parser("devices", help="talk to the robot's devices (or the simulated ones)")
    devsub = parser.add_subparsers(dest="devices_command", metavar="ACTION")
    # `read` (serial devices) and `check` (the whole set) live in their own modules
    for name in ("acquisition.cli.devices_read", "acquisition.cli.devices_check"):
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue
            raise
        module.register(devsub)
