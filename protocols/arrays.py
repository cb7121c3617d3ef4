"""The wire form of an n-d array: ``{"dtype": str, "shape": [int, ...], "data": bin}``, never a pickle.

``data`` holds the elements in C (row-major) order, little-endian, exactly ``prod(shape) * itemsize`` bytes.
"""

from __future__ import annotations

import numpy as np

from .errors import ProtocolError

# wire dtype name -> numpy dtype (explicit little-endian: the wire byte order, whatever the host's)
DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype("<u1"),
    "uint16": np.dtype("<u2"),
    "int32": np.dtype("<i4"),
    "int64": np.dtype("<i8"),
    "float32": np.dtype("<f4"),
    "float64": np.dtype("<f8"),
}
_NAMES = {dt: name for name, dt in DTYPES.items()}
MAX_NDIM = 4


def encode_array(array: np.ndarray) -> dict:
    """Returns the wire dict of ``array`` (dtype one of DTYPES, any shape)."""
    array = np.asarray(array)
    dtype = array.dtype.newbyteorder("<")
    if dtype not in _NAMES:
        raise ProtocolError("bad_request", f"dtype {array.dtype} cannot travel on the wire")
    data = np.ascontiguousarray(array, dtype=dtype).tobytes()
    return {"dtype": _NAMES[dtype], "shape": [int(n) for n in array.shape], "data": data}


def decode_array(
    obj: object, name: str, dtypes: tuple[str, ...], ndim: tuple[int, ...], max_elements: int
) -> np.ndarray:
    """Returns the read-only array in wire dict ``obj``; ProtocolError(bad_request/too_large) otherwise.

    dtypes: allowed wire dtype names; ndim: allowed numbers of dimensions.
    """
    if not isinstance(obj, dict):
        raise ProtocolError("bad_request", f"{name} must be an array map {{dtype, shape, data}}")
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dtype not in dtypes:
        raise ProtocolError("bad_request", f"{name}.dtype must be one of {', '.join(dtypes)}, got {dtype!r}")
    if not isinstance(shape, list) or len(shape) not in ndim:
        raise ProtocolError("bad_request", f"{name}.shape must be a list of {ndim} dimension(s)")
    if not all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n for n in shape):
        raise ProtocolError("bad_request", f"{name}.shape must hold non-negative integers, got {shape}")
    count = 1
    for n in shape:  # python ints: a huge declared shape cannot overflow
        count *= n
    if count > max_elements:
        raise ProtocolError("too_large", f"{name} declares {count} elements; the limit is {max_elements}")
    if not isinstance(data, bytes) or len(data) != count * DTYPES[dtype].itemsize:
        raise ProtocolError("bad_request", f"{name}.data must be {count * DTYPES[dtype].itemsize} bytes")
    return np.frombuffer(data, dtype=DTYPES[dtype]).reshape(shape)
