"""The `cdpr` console script: one argparse front end over per-topic command modules.

Each module in ``COMMAND_MODULES`` exposes ``register(subparsers)``, which adds its sub-commands and sets
``func`` on their parsers. ``func(args) -> int`` returns the exit status. Errors follow the contract of
../shared/spec/cli.md: one sentence on stderr, exit 2 for bad input (:class:`UsageError`), 1 for a failed
operation (:class:`OperationError`); ``--debug`` shows the traceback. A warning of the project's code
(a ``UserWarning``: damaged lines skipped, a log cut short) is one line ``cdpr: warning: ...``.

SIGINT and SIGTERM are routed to :class:`KeyboardInterrupt` from the first line of :func:`main`, before the
command modules are imported, so a stop at any moment ends in one sentence; a command that owns the stop
(`cdpr startup`'s safety supervisor) installs its own handlers over these and restores them.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import warnings

from calib.errors import CdprError

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
    "acquisition.cli.study",
)

# the module that registers each top-level command: a command line that names one imports only its module
COMMAND_OWNERS = {
    "robot": "acquisition.cli.robot",
    "poses": "acquisition.cli.poses",
    "workspace": "acquisition.cli.poses",
    "solve": "acquisition.cli.solve",
    "import": "acquisition.cli.runs",
    "export": "acquisition.cli.runs",
    "devices": "acquisition.cli.devices",
    "startup": "acquisition.cli.startup",
    "replay": "acquisition.cli.replay",
    "diagnose": "acquisition.cli.diagnose",
    "certify": "acquisition.cli.certify",
    "study": "acquisition.cli.study",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:
        """argparse's own usage errors: exit 2, one sentence that points at the command's help (the usage block
        argparse prints first took 5 to 8 lines before the sentence)."""
        prog = self.prog if self.prog != "cdpr" else " ".join(("cdpr", *self.command[:1]))
        sys.stderr.write(f"cdpr: {message.rstrip('.')}; see `{prog} --help`.\n")
        raise SystemExit(2)

    command: tuple[str, ...] = ()  # the top parser: the command named, whose help an unknown option points at


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("cdpr")
    except PackageNotFoundError:  # run from a checkout that was not installed
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``--version``: print the installed version and exit, read only when asked (importlib.metadata costs
    ~0.05 s that every other command skips)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"cdpr {_version()}")
        parser.exit()


def modules_for(argv: list[str]) -> tuple[str, ...]:
    """The command modules a parse of ``argv`` needs: the named command's alone, none for a bare ``--version``.

    Importing a module is what costs (scipy, python-can, codac...); the parse is the same as with every module
    registered whenever the command is known. Help, no command or an unknown one: every module.
    """
    for token in argv:
        if token in ("-h", "--help"):
            return COMMAND_MODULES
        if not token.startswith("-"):
            owner = COMMAND_OWNERS.get(token)
            return (owner,) if owner in COMMAND_MODULES else COMMAND_MODULES
        if token == "--version":
            return ()
    return COMMAND_MODULES


def build_parser(modules: tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The ``cdpr`` parser with the commands of ``modules`` (default: every command module)."""
    parser = _Parser(prog="cdpr", description="Self-calibration of underactuated cable-driven parallel robots.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action=_VersionAction, help="print the installed version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES if modules is None else modules:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a command module not written yet in this checkout
            if exc.name == name:
                continue
            raise
        module.register(sub)
    return parser


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM received while no command owned the stop; ``args[0]`` is the signal's name."""


def _interrupt(signum, frame) -> None:
    raise Interrupted(signal.Signals(signum).name)


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    if issubclass(category, UserWarning):
        sys.stderr.write(f"cdpr: warning: {message}\n")
    else:  # a library's own warning (numpy, matplotlib): as Python shows it
        _show_warning(message, category, filename, lineno, file, line)


_show_warning = warnings.showwarning


def _route_signals() -> dict:
    """SIGINT and SIGTERM raise :class:`Interrupted` (main thread only: elsewhere Python allows no handler)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that Python's flush at exit does not raise BrokenPipeError again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout is not a file descriptor (captured in tests)
        pass


def main(argv: list[str] | None = None) -> int:
    previous = _route_signals()
    started: list[str] = []  # the command, once it runs
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", UserWarning)
            warnings.showwarning = _warning_line
            return _main(argv, started)
    except KeyboardInterrupt as exc:
        name = exc.args[0] if isinstance(exc, Interrupted) else "SIGINT"
        when = f" during cdpr {started[0]}" if started else " before the command started; nothing was written"
        sys.stderr.write(f"cdpr: interrupted by the operator ({name}){when}.\n")
        return 1
    except BrokenPipeError:  # the reader of stdout left (`cdpr poses --json | head`): end quietly, as Unix tools do
        _silence_stdout()
        return 141  # 128 + SIGPIPE, what a shell reports for a tool the pipe ended
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


LENGTH_OPTIONS = ("--tolerance",)  # options whose value is a length: a leading '-' there is a sign, not an option


def _join_signed_values(argv: list[str]) -> list[str]:
    """``--tolerance -3mm`` as ``--tolerance=-3mm``: argparse would read ``-3mm`` as an unknown option and say
    only "expected one argument"; joined, the value reaches ``acquisition.plans.parse_length``, which says
    what is wrong."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in LENGTH_OPTIONS and i + 1 < len(argv) and argv[i + 1][:1] == "-" and (
                argv[i + 1][1:2].isdigit() or argv[i + 1][1:2] == "."):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def _main(argv: list[str] | None, started: list[str]) -> int:
    argv = _join_signed_values(sys.argv[1:] if argv is None else list(argv))
    parser = build_parser(modules_for(argv))
    parser.command = tuple(t for t in argv if t in COMMAND_OWNERS)[:1]
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):  # no command, or a command without its action (`cdpr import`): its help
        sub = next((a.choices.get(args.command) for a in parser._actions
                    if isinstance(a, argparse._SubParsersAction)), None) if args.command else None
        (sub or build_parser()).print_help(sys.stderr)
        return 2
    started.append(str(args.command))
    try:
        return int(args.func(args) or 0)
    except CdprError as exc:  # every error of the project, mapped here once
        if args.debug:
            raise
        sys.stderr.write(f"cdpr: {exc}\n")
        return exc.exit_status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
