"""Option values and outputs shared by several commands: parsers and checks (bad values raise UsageError,
exit 2) and the CLI side of the output policy (acquisition/outputs.py)."""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

import numpy as np

from acquisition.cli.errors import UsageError

if TYPE_CHECKING:
    from acquisition.outputs import Replaced


def parse_pose(text: str | None, option: str = "--reference") -> np.ndarray | None:
    """A pose x,y,z,roll,pitch,yaw (m, rad) from a comma-separated option value, or None."""
    if text is None:
        return None
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != 6 or not all(math.isfinite(v) for v in vals):
        raise UsageError(f"{option} '{text}' must be six numbers x,y,z,roll,pitch,yaw (m, rad).")
    return np.array(vals)


FORCE_HELP = "move an existing output aside (kept as NAME.replaced-<time>) instead of refusing"


def add_force(parser) -> None:
    """The --force option of a command that writes outputs (acquisition/outputs.py)."""
    parser.add_argument("--force", action="store_true", help=FORCE_HELP)


def add_effect_options(parser) -> None:
    """The options `cdpr solve` gains from the effect library (issue 7): --effects and --effects-from (read
    by acquisition/cli/effect_options.py only when given, so a plain solve loads no effect library)."""
    parser.add_argument("--effects", default=None, metavar="A,B",
                        help="physical effects to include in the model (see cdpr diagnose)")
    parser.add_argument("--effects-from", action="append", default=[], metavar="MODULE",
                        help="a Python file or module defining more effects (repeatable)")


def check_output_option(path, force: bool, option: str, inputs=()) -> None:
    """Refuse, before any work, an output that exists and may not be replaced, or that is, holds or is inside
    one of the command's ``inputs`` (one sentence, exit 2)."""
    from acquisition.outputs import OutputExistsError, check_output  # here: `cdpr solve` writes no output

    try:
        check_output(path, force, option, inputs)
    except OutputExistsError as exc:
        raise UsageError(str(exc)) from exc


def claim_output_option(path, force: bool, option: str, inputs=()) -> Replaced | None:
    """Free an output path for writing (its missing folders made); with --force what was there is moved aside
    and the user told where."""
    from acquisition.outputs import OutputExistsError, claim_output

    try:
        replaced = claim_output(path, force, option, inputs)
    except OutputExistsError as exc:
        raise UsageError(str(exc)) from exc
    if replaced is not None:
        sys.stderr.write(f"cdpr: note: {replaced.sentence()}\n")
    return replaced
