"""One exception base for the library; bad input is also a ``ValueError``.

A frame that cannot be localized is not an error: it is ``Registration(success=False, reason=...)``.
"""

import numpy as np

# coordinates farther out than this (pixels, metres, a focal length in pixels) are no image's, map's or
# camera's: Earth-centred metres are 6.4e6, and squares of 1e9 stay far from overflow, which 1e200 (a
# mistyped unit or a bad cast) does not
MAX_COORDINATE = 1e9


def beyond_bound(values: np.ndarray) -> int | None:
    """Returns the first row (first index of a 1-D array) of finite ``values`` holding a number farther out
    than ``MAX_COORDINATE``, None if there is none."""
    far = np.abs(values) > MAX_COORDINATE
    return int(np.argwhere(far)[0, 0]) if far.any() else None


class LineregError(Exception):
    """Base of every error linereg raises on purpose."""


class InvalidInputError(LineregError, ValueError):
    """An argument has the wrong shape, type or value; the message names the argument."""


class FileFormatError(LineregError, ValueError):
    """A file cannot be read: missing, unreadable, corrupt, unsupported or of another format version."""
