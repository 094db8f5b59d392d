"""Errors the user can act on: the CLI prints their message alone (no traceback) and exits 2.

Subclass :class:`SkycapError` for anything caused by input, configuration or environment; the message
names the problem and the fix.
"""


class SkycapError(Exception):
    """Base of the user-facing errors."""
