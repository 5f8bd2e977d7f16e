"""Error types the CLI maps to exit statuses (2: bad input, 1: failed operation)."""

from calib.errors import CdprError


class UsageError(CdprError):
    """Bad input from the user: a file, field or value that cannot be used. Exit status 2."""

    exit_status = 2


class OperationError(CdprError):
    """An operation that was valid but failed (no convergence, device fault, safe stop). Exit status 1."""
