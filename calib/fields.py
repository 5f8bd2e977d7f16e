"""The one YAML reader of the project's description files (robot, simulator, devices): read and parse a file,
and typed access to its fields whose errors are one sentence naming the file, field and value.

calib/ imports nothing of the other packages, so drivers/ and sim_backend/ build their readers on this one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

QUOTE_LIMIT = 60  # characters of a quoted value at most


def quote(value: Any, limit: int = QUOTE_LIMIT) -> str:
    """``repr(value)`` cut at its first line break and to ``limit`` characters, with '...' where cut: a whole
    file read as one YAML scalar becomes its first line, not 380,000 characters."""
    text = repr(value)
    first = text.split("\\n", 1)[0].split("\n", 1)[0]
    return text if first == text and len(text) <= limit else first[:limit].rstrip() + "..."


def read_yaml(path: str | Path, error: type[Exception], what: str, end: str = ".") -> Any:
    """The parsed content of the YAML file ``path`` (a ``what``: 'robot description'...); an unreadable file
    or bad YAML raises ``error`` with one sentence (the parser's first line), closed by ``end``."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise error(f"{p}: cannot read the {what} ({exc.strerror or exc}){end}") from exc
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(f"{p}: not valid YAML ({str(exc).splitlines()[0]}){end}") from exc


class FieldReader:
    """Typed access to the fields of a mapping read from ``origin``; errors are ``error`` sentences closed by
    ``end``. A file kind subclasses it with its error class and the checks of its own schema."""

    error: type[Exception] = ValueError
    end = "."

    def __init__(self, origin: str):
        self.origin = origin

    def fail(self, fld: str, value: Any, why: str) -> Exception:
        """The error for field ``fld`` holding ``value`` that ``why`` ('must be positive')."""
        return self.error(f"{self.origin}: field '{fld}' = {quote(value)} {why}{self.end}")

    def missing(self, fld: str) -> Exception:
        """The error for the required field ``fld`` (dotted path) that is absent."""
        return self.error(f"{self.origin}: required field '{fld}' is missing{self.end}")

    def finite(self, value: Any, fld: str) -> float:
        """``value`` as a float, or the error unless it is a finite number (a bool is not)."""
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise self.fail(fld, value, "must be a finite number")
        return float(value)
