"""One line of an exception, for the kit's one-line error messages."""

from __future__ import annotations

__all__ = ["first_line"]


def first_line(err: BaseException, *, with_type: bool = False) -> str:
    """The first line of ``str(err)`` (stripped), or the exception's type name if it is empty.

    ``with_type=True`` prefixes the type name (``"ValueError: bad shape"``) and drops a
    trailing full stop, for a message that quotes a user's code raising it.

    >>> first_line(ValueError("bad shape\\n  at line 3"))
    'bad shape'
    >>> first_line(KeyError())
    'KeyError'
    >>> first_line(RuntimeError("no env."), with_type=True)
    'RuntimeError: no env'
    """
    text = str(err).strip()
    first = text.splitlines()[0] if text else ""
    if not with_type:
        return first or type(err).__name__
    first = first.rstrip(".")
    return f"{type(err).__name__}: {first}" if first else type(err).__name__
