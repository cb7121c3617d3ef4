"""One exception base for the library; bad input is also a ``ValueError``.

A frame that cannot be localized is not an error: it is ``Registration(success=False, reason=...)``.
"""

# coordinates farther out than this (pixels, metres, a focal length in pixels) are no image's, map's or
# camera's: Earth-centred metres are 6.4e6, and squares of 1e9 stay far from overflow, which 1e200 (a
# mistyped unit or a bad cast) does not
MAX_COORDINATE = 1e9


class LineregError(Exception):
    """Base of every error linereg raises on purpose."""


class InvalidInputError(LineregError, ValueError):
    """An argument has the wrong shape, type or value; the message names the argument."""


class FileFormatError(LineregError, ValueError):
    """A file cannot be read: missing, unreadable, corrupt, unsupported or of another format version."""
