"""One error type for bad input: the CLI prints it as one line, never a traceback."""
from __future__ import annotations


class FastneusError(Exception):
    """Bad input or a failed precondition a user can fix.

    Args:
        message: what is wrong and, where it helps, what to do.
        file: the file (or folder) concerned, if any.
        field: the field/key inside that file, if any (dotted path, e.g. ``frames[3].image``).
    """

    def __init__(self, message: str, file: str | None = None, field: str | None = None):
        self.message = message
        self.file = str(file) if file is not None else None
        self.field = field
        where = ": ".join(p for p in (self.file, self.field) if p)
        super().__init__(_one_line(f"{where}: {message}" if where else message))


def _one_line(text: str) -> str:
    """Escape line breaks and other unprintable characters (a file name or key from the input may
    hold them): the CLI prints every error as exactly one line."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() or c == "\t" else repr(c)[1:-1] for c in text)
