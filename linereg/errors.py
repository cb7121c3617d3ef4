"""One exception base for the library; bad input is also a ``ValueError``.

A frame that cannot be localized is not an error: it is ``Registration(success=False, reason=...)``.
"""


class LineregError(Exception):
    """Base of every error linereg raises on purpose."""


class InvalidInputError(LineregError, ValueError):
    """An argument has the wrong shape, type or value; the message names the argument."""


class FileFormatError(LineregError, ValueError):
    """A file cannot be read: missing, unreadable, corrupt, unsupported or of another format version."""
