"""The output policy of every `cdpr` command: nothing that exists is overwritten or written into.

An output a user names (a run folder, an exported file, a plot, a report) must not exist yet, or be an
empty folder. With ``--force`` what is there is moved aside to ``NAME.replaced-YYYYmmdd-HHMMSS`` (a
``-2``, ``-3``... suffix when that name is taken too), never deleted, and the command says where it went.
Two outputs are refused even with ``--force``: a file of a run folder (``run.yaml``, ``samples.csv``: the
log itself) and a folder that holds the current directory (moving it aside would pull the shell's folder
from under it).

Files a command derives from a run and keeps inside it (``solution.json``, ``offsets.yaml``,
``report.html``, ``effects_chi2.png``) are not outputs in this sense: the command that owns them rewrites
them, since the run they are computed from is kept (``solution.json`` only when asked: `cdpr solve --save`,
or its first solve with the default options).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from calib.errors import CdprError

RUN_FILES = ("run.yaml", "samples.csv")


class OutputExistsError(CdprError, ValueError):
    """An output that exists and may not be replaced; the message is one sentence naming it and the option."""


@dataclass(frozen=True)
class Replaced:
    """What ``claim_output`` moved aside: the output's path and the name it is kept under."""

    path: Path
    kept: Path

    def sentence(self) -> str:
        return f"{self.path} existed; it is kept as {self.kept}."


def _is_run_file(path: Path) -> bool:
    return path.name in RUN_FILES and (path.parent / "run.yaml").is_file()


def _holds_cwd(path: Path) -> bool:
    cwd = Path.cwd().resolve()
    target = path.resolve()
    return cwd == target or target in cwd.parents


def _occupied(path: Path) -> bool:
    """True when writing ``path`` would replace something: a file, or a folder that is not empty."""
    if path.is_dir() and not path.is_symlink():
        return any(path.iterdir())
    return path.exists() or path.is_symlink()


def _input_clash(path: Path, inputs: Iterable[str | Path]) -> str | None:
    """How ``path`` overlaps one of ``inputs`` (is it, is inside it, holds it), or None."""
    target = path.resolve()
    for given in inputs:
        source = Path(given).resolve()
        if target == source:
            return f"is the input {given}"
        if source in target.parents:
            return f"is inside the input {given}"
        if target in source.parents:
            return f"holds the input {given}"
    return None


def _unwritable_parent(path: Path) -> str | None:
    """Why the folder of ``path`` cannot be made and written (its nearest existing ancestor), or None."""
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"{parent} is not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"the folder {parent} is not writable"
    return None


def check_output(path: str | Path, force: bool, option: str, inputs: Iterable[str | Path] = ()) -> None:
    """Raise OutputExistsError when ``path`` (given with ``option``) exists and may not be replaced, overlaps
    one of the command's ``inputs``, or lies where no folder can be made."""
    path = Path(path)
    if _is_run_file(path):
        raise OutputExistsError(
            f"{option} {path} is the log of the run in {path.parent}; write the output elsewhere."
        )
    clash = _input_clash(path, inputs)
    if clash:
        raise OutputExistsError(f"{option} {path} {clash}; write the output elsewhere (even --force cannot).")
    why = _unwritable_parent(path)
    if why:
        raise OutputExistsError(f"{option} {path} cannot be written: {why}.")
    if not _occupied(path):
        return
    if not force:
        what = "holds files" if path.is_dir() else "exists"
        if path.is_dir() and any((path / f).exists() for f in RUN_FILES):
            what = "holds a run"
        raise OutputExistsError(
            f"{option} {path} already {what}; give another name, or --force to move it aside "
            f"(kept as {path.name}.replaced-<time>)."
        )
    if path.is_dir() and _holds_cwd(path):
        raise OutputExistsError(f"{option} {path} holds the current folder; it cannot be moved aside.")


def kept_name(path: Path, now: datetime | None = None) -> Path:
    """``path`` with ``.replaced-YYYYmmdd-HHMMSS`` appended (and ``-2``, ``-3``... while that exists)."""
    stamp = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    kept = path.with_name(f"{path.name}.replaced-{stamp}")
    k = 2
    while kept.exists() or kept.is_symlink():
        kept = path.with_name(f"{path.name}.replaced-{stamp}-{k}")
        k += 1
    return kept


def claim_output(path: str | Path, force: bool, option: str, inputs: Iterable[str | Path] = ()) -> Replaced | None:
    """Make ``path`` free to write: check it (see :func:`check_output`), create its missing parent folders
    and, with ``force``, move what is there aside. Returns what was moved, or None; an empty folder is left
    in place and used."""
    path = Path(path)
    check_output(path, force, option, inputs)
    path.absolute().parent.mkdir(parents=True, exist_ok=True)
    if not _occupied(path):
        return None
    kept = kept_name(path)
    path.rename(kept)
    return Replaced(path, kept)
