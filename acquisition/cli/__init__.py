"""The `cdpr` console script: one argparse front end over per-topic command modules.

Each module in ``COMMAND_MODULES`` exposes ``register(subparsers)``, which adds its sub-commands and sets
``func`` on their parsers. ``func(args) -> int`` returns the exit status. Errors follow the contract of
../shared/spec/cli.md: one sentence on stderr, exit 2 for bad input (:class:`UsageError`), 1 for a failed
operation (:class:`OperationError`); ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from acquisition.cli.errors import OperationError, UsageError

COMMAND_MODULES = (
    "acquisition.cli.robot",
    "acquisition.cli.poses",
    "acquisition.cli.solve",
    "acquisition.cli.runs",
    "acquisition.cli.devices",
    "acquisition.cli.startup",
    "acquisition.cli.replay",
    "acquisition.cli.diagnose",
    "acquisition.cli.certify",
)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # argparse's own usage errors: exit 2, one sentence
        self.print_usage(sys.stderr)
        sys.stderr.write(f"cdpr: {message}\n")
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cdpr", description="Self-calibration of underactuated cable-driven parallel robots.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a command module not written yet in this checkout
            if exc.name == name:
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:
        if args.debug:
            raise
        sys.stderr.write(f"cdpr: {exc}\n")
        return 2
    except OperationError as exc:
        if args.debug:
            raise
        sys.stderr.write(f"cdpr: {exc}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("cdpr: interrupted by the operator.\n")
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
