"""Every option of every `cdpr` subcommand has help text, found by walking the parser (so that options added
later are covered too); `cdpr --version` prints the installed package's version."""

from __future__ import annotations

import argparse
import subprocess
import sys
from importlib.metadata import version

from acquisition.cli import build_parser


def _walk(parser: argparse.ArgumentParser, path: str):
    """(command path, action) for every action of the parser and of its subcommands, recursively."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:  # the subcommand's own line in its parent's help
                yield f"{path} {choice.dest}", choice
            for name, sub in action.choices.items():
                yield from _walk(sub, f"{path} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield path, action


def test_every_option_of_every_subcommand_has_help():
    found = list(_walk(build_parser(), "cdpr"))
    missing = [f"{path}: {'/'.join(a.option_strings) or a.dest}" for path, a in found
               if not a.help or a.help == argparse.SUPPRESS or not a.help.strip()]
    assert not missing, "options without help text:\n" + "\n".join(missing)
    commands = {path for path, _ in found}
    # the walk reaches the nested subcommands (and so whatever is added later)
    assert {"cdpr import irma", "cdpr certify simulate", "cdpr devices read", "cdpr startup"} <= commands
    assert len(found) > 100


def test_the_help_of_commands_that_write_says_what_happens_to_an_existing_output():
    parser = build_parser()
    writers = {"startup": "--out", "import irma": "--out", "export": "--out", "diagnose": "--html",
               "certify simulate": "--output", "workspace": "--plot"}
    for command, option in writers.items():
        sub = parser
        for word in command.split():
            sub = next(a for a in sub._actions if isinstance(a, argparse._SubParsersAction)).choices[word]
        helps = {o: a.help for a in sub._actions for o in a.option_strings}
        assert "refused unless --force" in helps[option], command
        assert "moved aside" in helps["--force"] or "move an existing output aside" in helps["--force"], command


def test_version_is_the_installed_package_version():
    out = subprocess.run([sys.executable, "-c", "import sys; from acquisition.cli import main; sys.exit(main())",
                          "--version"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout == f"cdpr {version('cdpr')}\n", out
