"""The lists a KD-tree ball query returns (``cKDTree.query_ball_point``), as flat arrays."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np


def flat_lists(found: Sequence[Sequence[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((q,) int64 size of each of the q lists, int64 their entries one list after another)."""
    sizes = np.fromiter(map(len, found), np.int64, len(found))
    return sizes, np.fromiter(itertools.chain.from_iterable(found), np.int64, int(sizes.sum()))
