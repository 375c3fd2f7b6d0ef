"""The package's error types, the one way to quote an exception in a one-line message, and the one check of an
integer argument.

:class:`InputError` is what every check of a user's input raises: one line ``<role> '<path>': expected ..., got ...``.
"""

from __future__ import annotations

__all__ = ["InputError", "UntrustedFileError", "check_integer", "first_line"]


class InputError(ValueError):
    """A user input that cannot be used; ``str(error)`` is one line naming the file and the problem."""


class UntrustedFileError(InputError):
    """A weights file that is not a plain state dict: ``torch.load(weights_only=True)`` refused to unpickle it."""


def first_line(err: BaseException, limit: int | None = 160) -> str:
    """The first non-blank line of ``str(err)``, at most ``limit`` characters (the type name if it has none): how
    an underlying error is quoted inside a one-line message (``limit=None``: the whole line)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return (lines[0] if lines else type(err).__name__)[:limit]


def check_integer(name: str, value: object, minimum: int) -> int:
    """``value`` when it is an integer >= ``minimum`` (a bool is not: ``True`` would pass as 1); else ValueError
    ``<name> must be an integer >= <minimum>; got <value>``: the check of every integer setting of the blocks,
    losses and refinement."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return value
