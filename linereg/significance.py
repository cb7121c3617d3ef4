"""Could chance have given a pose its agreement with the image? An a-contrario test (Desolneux, Moisan and
Morel, "From Gestalt Theory to Image Analysis", 2008: the number of false alarms).

The background model: the pose's projected map, but placed at a uniformly random offset in the image. A
projected map segment then explains an image segment (covers ``min_cover`` of it: the score's test) for the
offsets of an area ``_chance_areas`` computes exactly (for a parallel map segment of length M >= min_cover
x L, a band 2 x ``distance_px`` wide and M + (1 - 2 min_cover) L long); summed over the image's segments, map
segment j is backed by some image segment with probability ``q_j = 1 - exp(-areas / image area)`` (a
Poisson count of chance covers).

X, the number of visible map segments backed by chance, is a sum of independent Bernoulli(q_j) draws; a pose
whose matches use k distinct map segments has ``P(X >= k)``. Draws and count are both per map segment: LSD
cuts one image line into fragments, and one long map line placed on it by chance explains them all (a wrong
demo pose matched 24 image segments with 9 map segments), so counting image segments would count one chance
event many times. The search tried many poses, so the expected number of chance poses doing as well is
``NFA = tests x P(X >= k)``, where ``tests`` counts the poses the search could tell apart
(``SearchSpace.log10_tests``). ``NFA >= 1``: the search would have found such an agreement with a map that
has nothing to do with the image, so it is no evidence of the pose. The test needs no rival to be found: in
a sparse image (tens of segments) a chance pose explaining a quarter of it can stand alone.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from .camera import Camera
from .config import RegisterConfig
from .geometry import segment_angles, segment_lengths
from .score import ImageLines
from .search import transform_depths


@dataclass(frozen=True)
class SearchSpace:
    """What a search examined: camera centres in boxes of ``volume_m3`` in all, about each of ``rotations``
    candidate rotations, each known to within ``rotation_tolerance_deg``."""

    volume_m3: float
    rotations: int
    rotation_tolerance_deg: float

    @staticmethod
    def of(
        regions: list[tuple[np.ndarray, np.ndarray]], rotations: int, config: RegisterConfig
    ) -> SearchSpace:
        """Returns the space of a search over boxes ``regions`` ((3,) low, (3,) high corners, m)."""
        volume = sum(float(np.prod(np.maximum(np.asarray(hi) - np.asarray(lo), 0.0))) for lo, hi in regions)
        return SearchSpace(volume, rotations, config.rotation.pair_angle_tolerance_deg)

    def log10_tests(self, camera: Camera, depth_m: float, distance_px: float) -> float:
        """Returns log10 of the number of poses the search could tell apart in an image of ``camera`` whose
        map lies ``depth_m`` away: rotations at the angle of ``distance_px`` (a turn moving the projection
        by that much) within the tolerance of each candidate, camera centres at the step that moves a point
        at ``depth_m`` by ``distance_px``."""
        focal = 0.5 * (camera.fx + camera.fy)
        turn = math.degrees(distance_px / focal)
        step = distance_px * max(depth_m, 1e-6) / focal
        rotations = math.log10(max(self.rotations, 1)) + 3 * math.log10(
            max(self.rotation_tolerance_deg / turn, 1.0)
        )
        return rotations + math.log10(max(self.volume_m3 / step**3, 1.0))


def chance_probabilities(
    image: ImageLines,
    projected: np.ndarray,
    distance_px: float,
    angle_deg: float,
    min_cover: float,
    among: np.ndarray | None = None,
) -> np.ndarray:
    """Returns (K,) the probability that each of (K, 4) projected map segments, placed at a uniformly random
    offset in the image, explains some image segment (the background model above); ``among``: (N,) bool,
    only those image segments (None: all)."""
    projected = np.ascontiguousarray(projected, dtype=np.float64).reshape(-1, 4)
    lengths, angles = (
        (image.lengths, image.angles) if among is None else (image.lengths[among], image.angles[among])
    )
    area = _chance_areas(
        lengths, angles, segment_lengths(projected), segment_angles(projected), distance_px,
        math.radians(angle_deg), min_cover,
    )  # fmt: skip
    return -np.expm1(-area / float(image.width * image.height))


def log10_tail(p: np.ndarray, k: int) -> float:
    """Returns log10 P(X >= k) for X the sum of independent Bernoulli(p) draws (exact; 0 for k <= 0)."""
    if k <= 0:
        return 0.0
    if k > len(p):
        return -math.inf
    tail = _tail(np.ascontiguousarray(p, dtype=np.float64), int(k))
    return math.log10(max(tail, 5e-324))  # below the smallest double: as unlikely as it can say


def log10_fisher(log10_p: Sequence[float]) -> float:
    """Returns log10 of the probability that K independent chance p-values multiply to no more than these
    (given as log10 p each; Fisher's combination, exact: P(p_1 ... p_K <= x) = x sum_{j<K} (-ln x)^j / j!).
    Evidence spread over several photos adds up; a photo holding none (p = 1) weakens the rest only by the
    count it adds. 0 for none; -inf if one is impossible by chance."""
    k = len(log10_p)
    if k == 0:
        return 0.0
    ln_x = math.log(10.0) * float(sum(log10_p))
    if not math.isfinite(ln_x):
        return -math.inf
    y = max(-ln_x, 0.0)
    if y == 0.0:
        return 0.0
    terms = [j * math.log(y) - math.lgamma(j + 1) for j in range(k)]
    top = max(terms)
    ln_sum = top + math.log(sum(math.exp(t - top) for t in terms))
    return min(0.0, (ln_x + ln_sum) / math.log(10.0))


def depth_of(segments: np.ndarray, cam_from_world: np.ndarray) -> float:
    """Returns the median depth (m) of the endpoints of (K, 6) world segments in front of a camera."""
    z = transform_depths(segments, cam_from_world)
    z = z[z > 0]
    return float(np.median(z)) if len(z) else 1.0


@numba.njit(cache=True)
def _chance_areas(
    lengths: np.ndarray,
    angles: np.ndarray,
    map_lengths: np.ndarray,
    map_angles: np.ndarray,
    distance: float,
    angle_tol: float,
    min_cover: float,
) -> np.ndarray:
    """(K,) px^2 of offsets at which each map segment explains some image segment, summed over them.

    The score's pair test (``score._covering_pairs``): the angle within ``max(angle_tol, atan(2 distance /
    L))``, and the whole shared stretch s within ``distance`` of the image line at both ends, which at an
    angle d leaves a band of offsets ``2 distance - s sin d`` wide. Sliding the map segment along the image
    segment, s ramps up over min(L, M) at each end and holds min(L, M) over |L - M| between: the area is
    the band width integrated over the slide where s >= min_cover x L.
    """
    out = np.zeros(len(map_lengths))
    for i in range(len(lengths)):
        need = min_cover * lengths[i]
        tol = max(angle_tol, np.arctan(2.0 * distance / lengths[i]))
        for j in range(len(map_lengths)):
            short = min(lengths[i], map_lengths[j])
            if short < need:
                continue
            gap = abs(angles[i] - map_angles[j])
            gap = min(gap, np.pi - gap)
            if gap > tol:
                continue
            sin = np.sin(gap)
            top = short if sin == 0.0 else min(short, 2.0 * distance / sin)
            area = 0.0
            if top > need:  # the two ramps
                area += 2.0 * (2.0 * distance * (top - need) - 0.5 * sin * (top * top - need * need))
            area += abs(lengths[i] - map_lengths[j]) * max(0.0, 2.0 * distance - short * sin)  # the plateau
            out[j] += area
    return out


@numba.njit(cache=True)
def _tail(p: np.ndarray, k: int) -> float:
    """P(sum of Bernoulli(p) >= k): the distribution of the count below k, with k absorbing."""
    dist = np.zeros(k + 1)
    dist[0] = 1.0
    for q in p:
        dist[k] += dist[k - 1] * q
        for c in range(k - 1, 0, -1):
            dist[c] = dist[c] * (1.0 - q) + dist[c - 1] * q
        dist[0] *= 1.0 - q
    return dist[k]
