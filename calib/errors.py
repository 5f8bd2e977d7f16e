"""The one base of the errors the project raises on purpose (every package may import it: it imports nothing).

Each error keeps its builtin base (a ``ValueError`` for bad input, a ``RuntimeError`` for a failed operation), so
code that catches those still does; the `cdpr` command maps a :class:`CdprError` that reaches it once, by
:attr:`CdprError.exit_status` (../shared/spec/cli.md: 2 bad input, 1 failed operation).
"""

from __future__ import annotations


class CdprError(Exception):
    """An error of the project whose message is one sentence naming the file, field and value."""

    @property
    def exit_status(self) -> int:
        """2 for bad input (a ``ValueError``), 1 for an operation that failed."""
        return 2 if isinstance(self, ValueError) else 1
