"""How an error sentence quotes a value a user gave: at most one line, cut to a readable length."""

from __future__ import annotations

from typing import Any

QUOTE_LIMIT = 60  # characters of a quoted value at most


def quote(value: Any, limit: int = QUOTE_LIMIT) -> str:
    """``repr(value)`` cut at its first line break and to ``limit`` characters, with '...' where cut: a whole
    file read as one YAML scalar becomes its first line, not 380,000 characters."""
    text = repr(value)
    first = text.split("\\n", 1)[0].split("\n", 1)[0]
    return text if first == text and len(text) <= limit else first[:limit].rstrip() + "..."
