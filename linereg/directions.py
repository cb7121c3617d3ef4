"""The shared result type of direction clustering, for 2D vanishing directions and 3D parallel sets."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DirectionClusters:
    """Dominant directions and which segments follow them.

    directions: (K, 3) float64 unit vectors, strongest cluster first. 2D vanishing directions are in the
        camera frame with z >= 0 (a VD's sign is arbitrary); 3D directions in the world frame.
    labels: (N,) int64 cluster index of each segment, -1 for none.
    support: (K,) float64 strength of each cluster (summed member length), descending.
    """

    directions: np.ndarray
    labels: np.ndarray
    support: np.ndarray

    def __len__(self) -> int:
        return len(self.directions)

    def members(self, k: int) -> np.ndarray:
        """Returns the (n_k,) indices of the segments of cluster k."""
        return np.flatnonzero(self.labels == k)


def subset_clusters(clusters: DirectionClusters, index: np.ndarray, lengths: np.ndarray) -> DirectionClusters:
    """Returns the clusters restricted to segments ``index`` (e.g. the visible part of a map).

    lengths: (len(index),) lengths of those segments, for the support. Directions keep their order even if
    the subset changes which cluster is strongest (the rotation stage only pairs them).
    """
    labels = clusters.labels[index]
    support = np.array([lengths[labels == k].sum() for k in range(len(clusters))], dtype=np.float64)
    return DirectionClusters(clusters.directions, labels, support)
