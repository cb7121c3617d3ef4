"""A procedural Manhattan building block: a clean surface model and its true 3D edges (views: ``views``).

World frame: metres, z up, ground at z = 0, facades along x and y (the three Manhattan directions).
Every face is a planar rectangle given as a quad whose corners run counter-clockwise seen from outside
(``(q1 - q0) x (q2 - q0)`` points out of the solid). Windows and doors are real holes with reveal quads
(the recess), so a renderer or a laser-scanner simulator sees the same 3D structure as ``edges``.
Walls are cut into rectangles around the openings, which leaves T-junctions between coplanar quads.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

logger = logging.getLogger(__name__)

FACE_KINDS = ("wall", "window", "door", "roof", "ground", "ledge")  # the materials a face can be
EDGE_KINDS = ("corner", "roof", "ground", "ledge", "window", "door")  # what an edge bounds
UP = np.array([0.0, 0.0, 1.0])  # the world's vertical (z up, ground at z = 0)
Range = tuple[float, float]


@dataclass(frozen=True)
class BuildingConfig:
    """Shape of the procedural building; ``(lo, hi)`` ranges are drawn uniformly per block."""

    layout: Literal["courtyard", "street"] = "courtyard"  # 4 blocks round a yard, or 2 rows along a street
    blocks_per_side: int = 2  # street layout: blocks in each row
    yard_m: Range = (6.0, 12.0)  # courtyard: half-size beyond the corner passages (yard 20-40 m across)
    street_width_m: Range = (16.0, 24.0)
    block_length_m: Range = (12.0, 28.0)  # street layout: facade length along the street
    depth_m: Range = (10.0, 14.0)  # block depth (wing thickness)
    gap_m: Range = (4.0, 8.0)  # passages between blocks
    floors: tuple[int, int] = (3, 6)
    floor_height_m: Range = (3.0, 3.6)
    window_spacing_m: Range = (2.8, 4.0)  # bay width of the window grid
    window_width_m: Range = (1.0, 1.6)
    window_height_m: Range = (1.3, 1.8)
    sill_height_m: float = 0.9  # window bottom above its floor
    recess_m: Range = (0.10, 0.15)  # windows and doors sit this deep in the wall
    door_width_m: Range = (1.2, 1.8)
    door_height_m: Range = (2.2, 2.5)
    door_probability: float = 0.7  # per facade, one door on the ground floor
    ledge_height_m: float = 0.25  # horizontal ledge between floors
    ledge_depth_m: float = 0.15  # how far it sticks out of the wall
    ground_margin_m: float = 15.0  # ground plane beyond the blocks
    recess_edges: bool = True  # also list the inner (recessed) outline of windows and doors as edges


@dataclass(frozen=True)
class Building:
    """Surface model and true edges of a building.

    faces: (F, 4, 3) float64 rectangles, CCW from outside; face_kind: (F,) str in ``FACE_KINDS``;
    face_block: (F,) int64 block index, -1 for the ground plane; edges: (E, 6) float64 segments;
    edge_kind: (E,) str in ``EDGE_KINDS``; blocks: (B, 2, 3) float64 min / max corner of each block's box
    (without ledges); bounds: (2, 3) float64 min / max of all faces.
    """

    faces: np.ndarray
    face_kind: np.ndarray
    face_block: np.ndarray
    edges: np.ndarray
    edge_kind: np.ndarray
    blocks: np.ndarray
    bounds: np.ndarray

    @property
    def normals(self) -> np.ndarray:
        """Returns (F, 3) outward unit normals of the faces."""
        n = np.cross(self.faces[:, 1] - self.faces[:, 0], self.faces[:, 2] - self.faces[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Returns ((4F, 3) vertices, (2F, 3) int64 triangles) of the faces: each rectangle as two triangles
        sharing its diagonal, in consecutive rows (as ``LineMap`` surfaces pair them back into rectangles)."""
        corner = 4 * np.arange(len(self.faces))
        triangles = np.stack(
            [np.c_[corner, corner + 1, corner + 2], np.c_[corner, corner + 2, corner + 3]], axis=1
        )
        return self.faces.reshape(-1, 3), triangles.reshape(-1, 3)


class _Frame(NamedTuple):
    """A plane with in-plane axes u, v and normal n = u x v: local (s, t, d) -> origin + s u + t v + d n."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    n: np.ndarray

    def lift(self, s, t, d=0.0) -> np.ndarray:
        s, t, d = np.broadcast_arrays(np.asarray(s, float), np.asarray(t, float), np.asarray(d, float))
        return self.origin + s[..., None] * self.u + t[..., None] * self.v + d[..., None] * self.n


class _Style(NamedTuple):
    floors: int
    floor_h: float
    spacing: float
    win_w: float
    win_h: float
    recess: float


class _Parts:
    """Accumulates faces and edges while a building is made."""

    def __init__(self) -> None:
        self.faces: list[np.ndarray] = []
        self.kinds: list[np.ndarray] = []
        self.blocks: list[np.ndarray] = []
        self.edges: list[np.ndarray] = []
        self.edge_kinds: list[np.ndarray] = []

    def face(self, quads: np.ndarray, kind: str, block: int) -> None:
        self.faces.append(quads.reshape(-1, 4, 3))
        self.kinds.append(np.full(len(self.faces[-1]), kind))
        self.blocks.append(np.full(len(self.faces[-1]), block, dtype=np.int64))

    def edge(self, segments: np.ndarray, kind: str) -> None:
        self.edges.append(segments.reshape(-1, 6))
        self.edge_kinds.append(np.full(len(self.edges[-1]), kind))


def _orient(quads: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Returns (Q, 4, 3) quads reordered where needed so that their corners run CCW around ``normals``."""
    n = np.cross(quads[:, 1] - quads[:, 0], quads[:, 2] - quads[:, 0])
    flip = np.einsum("qk,qk->q", n, np.broadcast_to(normals, n.shape)) < 0
    return np.where(flip[:, None, None], quads[:, ::-1], quads)


def _rect_quads(frame: _Frame, rects: np.ndarray, d: float = 0.0) -> np.ndarray:
    """Returns (Q, 4, 3) quads of local rectangles (Q, 4) ``s0, t0, s1, t1`` at depth d, CCW around n."""
    return frame.lift(rects[:, [0, 2, 2, 0]], rects[:, [1, 1, 3, 3]], d)


def _rect_edges(frame: _Frame, rects: np.ndarray, d: float = 0.0, sides=(0, 1, 2, 3)) -> np.ndarray:
    """Returns (Q * len(sides), 6) outline segments (0 bottom, 1 right, 2 top, 3 left) of local rectangles."""
    corners = _rect_quads(frame, rects, d)  # (Q, 4, 3): (s0,t0) (s1,t0) (s1,t1) (s0,t1)
    ends = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)[:, list(sides)]
    return ends.reshape(-1, 6)


def _reveal_quads(frame: _Frame, rects: np.ndarray, depth: float) -> np.ndarray:
    """Returns (Q, 4, 4, 3) left, right, bottom, top reveal quads of openings recessed ``depth`` into a wall."""
    s0, t0, s1, t1 = (rects[:, k : k + 1] for k in range(4))
    d = np.array([0.0, 0.0, -depth, -depth])
    sides = [
        (frame.lift(np.tile(s0, 4), np.c_[t0, t1, t1, t0], d), frame.u),
        (frame.lift(np.tile(s1, 4), np.c_[t0, t1, t1, t0], d), -frame.u),
        (frame.lift(np.c_[s0, s1, s1, s0], np.tile(t0, 4), d), frame.v),
        (frame.lift(np.c_[s0, s1, s1, s0], np.tile(t1, 4), d), -frame.v),
    ]
    return np.stack([_orient(q, n) for q, n in sides], axis=1)


def rect_minus(width: float, height: float, holes: np.ndarray) -> np.ndarray:
    """Returns (Q, 4) rectangles ``s0, t0, s1, t1`` covering [0, width] x [0, height] minus the holes.

    holes: (H, 4) non-overlapping rectangles inside the domain. Grid cells are merged into horizontal runs,
    then identical runs of consecutive rows into one rectangle.
    """
    xs = np.unique(np.r_[0.0, width, holes[:, [0, 2]].ravel()])
    ys = np.unique(np.r_[0.0, height, holes[:, [1, 3]].ravel()])
    cx, cy = 0.5 * (xs[:-1] + xs[1:]), 0.5 * (ys[:-1] + ys[1:])
    inx = (cx[None, :] > holes[:, 0:1]) & (cx[None, :] < holes[:, 2:3])  # (H, nx)
    iny = (cy[None, :] > holes[:, 1:2]) & (cy[None, :] < holes[:, 3:4])  # (H, ny)
    free = ~np.einsum("hy,hx->yx", iny.astype(int), inx.astype(int)).astype(bool)
    out: list[list[float]] = []
    open_runs: dict[tuple[int, int], int] = {}  # run of cells -> row where it began
    for j in range(len(cy)):
        edges = np.diff(np.r_[0, free[j].astype(int), 0])
        runs = set(
            zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True)
        )
        for run in set(open_runs) - runs:  # run ends below this row
            out.append([xs[run[0]], ys[open_runs.pop(run)], xs[run[1]], ys[j]])
        for run in runs - set(open_runs):
            open_runs[run] = j
    out += [[xs[r[0]], ys[j0], xs[r[1]], ys[-1]] for r, j0 in open_runs.items()]
    return np.array(out, dtype=np.float64).reshape(-1, 4)


def _openings(rng: np.random.Generator, cfg: BuildingConfig, style: _Style, length: float):
    """Returns ((W, 4) window, (D, 4) door) local rectangles of one facade of the given length."""
    bays = int((length - 2.0) // style.spacing)
    if bays < 1:
        return np.zeros((0, 4)), np.zeros((0, 4))
    centres = (length - bays * style.spacing) / 2 + (np.arange(bays) + 0.5) * style.spacing
    floor, col = np.meshgrid(np.arange(style.floors), np.arange(bays), indexing="ij")
    t0 = floor.ravel() * style.floor_h + cfg.sill_height_m
    s = centres[col.ravel()]
    windows = np.c_[s - style.win_w / 2, t0, s + style.win_w / 2, t0 + style.win_h]
    if rng.uniform() >= cfg.door_probability:
        return windows, np.zeros((0, 4))
    j = rng.integers(bays)
    width = min(rng.uniform(*cfg.door_width_m), style.spacing - 0.6)
    door = np.array([[centres[j] - width / 2, 0.0, centres[j] + width / 2, rng.uniform(*cfg.door_height_m)]])
    return windows[(floor.ravel() > 0) | (col.ravel() != j)], door


def _facade(parts: _Parts, rng, cfg: BuildingConfig, style: _Style, frame: _Frame, length: float, block: int):
    """Adds one facade: walls around openings and ledge bands, reveals, glass, doors and their edges."""
    height = style.floors * style.floor_h
    windows, doors = _openings(rng, cfg, style, length)
    zs = np.arange(1, style.floors) * style.floor_h
    bands = np.c_[
        np.zeros_like(zs), zs - cfg.ledge_height_m / 2, np.full_like(zs, length), zs + cfg.ledge_height_m / 2
    ]
    parts.face(_rect_quads(frame, rect_minus(length, height, np.r_[windows, doors, bands])), "wall", block)
    for rects, kind in ((windows, "window"), (doors, "door")):
        reveals = _reveal_quads(frame, rects, style.recess)
        parts.face(reveals[:, [0, 1, 3]], "wall", block)
        parts.face(
            reveals[:, 2], "ground" if kind == "door" else "wall", block
        )  # door recess floor is ground
        parts.face(_rect_quads(frame, rects, -style.recess), kind, block)
        parts.edge(_rect_edges(frame, rects, 0.0, (1, 2, 3) if kind == "door" else (0, 1, 2, 3)), kind)
        if cfg.recess_edges:
            parts.edge(_rect_edges(frame, rects, -style.recess), kind)
    parts.edge(_rect_edges(frame, np.array([[0.0, 0.0, length, height]]), 0.0, (0,)), "ground")
    parts.edge(_rect_edges(frame, np.array([[0.0, 0.0, length, height]]), 0.0, (2,)), "roof")
    cuts = np.r_[0.0, np.repeat(zs, 2) + np.tile([-1, 1], len(zs)) * cfg.ledge_height_m / 2, height]
    parts.edge(np.c_[frame.lift(0.0, cuts[0::2]), frame.lift(0.0, cuts[1::2])], "corner")  # corner at s = 0


def _ledges(
    parts: _Parts, cfg: BuildingConfig, frame: _Frame, length: float, zs: np.ndarray, extend: bool, b
):
    """Adds the ledges of one facade: front, top and bottom; x-facing ones cover the corners."""
    e, half = cfg.ledge_depth_m, cfg.ledge_height_m / 2
    for z in zs:
        front = np.array([[-e, z - half, length + e, z + half]])
        parts.face(_rect_quads(frame, front, e), "ledge", b)
        parts.edge(_rect_edges(frame, front, e, (0, 2)), "ledge")
        s0, s1 = (-e, length + e) if extend else (0.0, length)
        for t, up in ((z + half, 1.0), (z - half, -1.0)):
            quad = frame.lift([s0, s1, s1, s0], t, [0.0, 0.0, e, e])[None]
            parts.face(_orient(quad, up * UP), "ledge", b)


def _block(parts: _Parts, rng, cfg: BuildingConfig, footprint: np.ndarray, b: int) -> float:
    """Adds one box-shaped block (x0, y0, x1, y1) with its own style; returns its height."""
    style = _Style(
        int(rng.integers(cfg.floors[0], cfg.floors[1] + 1)),
        rng.uniform(*cfg.floor_height_m),
        rng.uniform(*cfg.window_spacing_m),
        rng.uniform(*cfg.window_width_m),
        rng.uniform(*cfg.window_height_m),
        rng.uniform(*cfg.recess_m),
    )
    x0, y0, x1, y1 = footprint
    height = style.floors * style.floor_h
    for frame, length, extend in block_facades(footprint):
        _facade(parts, rng, cfg, style, frame, length, b)
        _ledges(parts, cfg, frame, length, np.arange(1, style.floors) * style.floor_h, extend, b)
    roof = _Frame(np.array([x0, y0, height]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), UP)
    parts.face(_rect_quads(roof, np.array([[0.0, 0.0, x1 - x0, y1 - y0]])), "roof", b)
    return height


def block_facades(footprint: np.ndarray) -> list[tuple[_Frame, float, bool]]:
    """Returns (frame, length, x-facing) of the 4 facades of a footprint; frame u = z x n runs CCW round it."""
    x0, y0, x1, y1 = footprint
    out = []
    for normal, corner, length in (
        ((1.0, 0.0, 0.0), (x1, y0), y1 - y0),
        ((0.0, 1.0, 0.0), (x1, y1), x1 - x0),
        ((-1.0, 0.0, 0.0), (x0, y1), y1 - y0),
        ((0.0, -1.0, 0.0), (x0, y0), x1 - x0),
    ):
        n = np.array(normal)
        out.append((_Frame(np.array([*corner, 0.0]), np.cross(UP, n), UP, n), float(length), bool(n[0] != 0)))
    return out


def _layout(rng: np.random.Generator, cfg: BuildingConfig) -> np.ndarray:
    """Returns (B, 4) footprints ``x0, y0, x1, y1`` of disjoint blocks (every facade is a real facade)."""
    d, g = rng.uniform(*cfg.depth_m, size=4), rng.uniform(*cfg.gap_m)
    if cfg.layout == "courtyard":  # yard [-a, a] x [-b, b]; east / west wings stop g short of the others
        a, b = 0.5 * rng.uniform(20.0, 30.0), g + rng.uniform(*cfg.yard_m)
        return np.array(
            [
                [-a, -b - d[0], a, -b],
                [-a, b, a, b + d[1]],
                [-a - d[2], -b + g, -a, b - g],
                [a, -b + g, a + d[3], b - g],
            ]
        )
    if cfg.layout != "street":
        raise ValueError(f"unknown building layout {cfg.layout!r}")
    half, rows = rng.uniform(*cfg.street_width_m) / 2, []
    for side in (-1.0, 1.0):
        x = rng.uniform(-5.0, 5.0) - 0.5 * cfg.blocks_per_side * np.mean(cfg.block_length_m)
        for _ in range(cfg.blocks_per_side):
            length, depth = rng.uniform(*cfg.block_length_m), rng.uniform(*cfg.depth_m)
            y = (half, half + depth) if side > 0 else (-half - depth, -half)
            rows.append([x, y[0], x + length, y[1]])
            x += length + rng.uniform(*cfg.gap_m)
    return np.array(rows)


def make_building(rng: np.random.Generator, config: BuildingConfig | None = None) -> Building:
    """Returns a procedural Manhattan building (blocks, windows grids, doors, ledges, ground) in metres."""
    cfg = config or BuildingConfig()
    parts, footprints = _Parts(), _layout(rng, cfg)
    heights = [_block(parts, rng, cfg, fp, b) for b, fp in enumerate(footprints)]
    lo, hi = footprints[:, :2].min(0) - cfg.ground_margin_m, footprints[:, 2:].max(0) + cfg.ground_margin_m
    ground = _Frame(np.array([*lo, 0.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), UP)
    holes = footprints - np.r_[lo, lo]
    parts.face(
        _rect_quads(ground, rect_minus(float(hi[0] - lo[0]), float(hi[1] - lo[1]), holes)), "ground", -1
    )
    faces = np.concatenate(parts.faces)
    blocks = np.stack(
        [np.c_[footprints[:, :2], np.zeros(len(footprints))], np.c_[footprints[:, 2:], heights]], 1
    )
    building = Building(
        faces=faces,
        face_kind=np.concatenate(parts.kinds),
        face_block=np.concatenate(parts.blocks),
        edges=np.concatenate(parts.edges),
        edge_kind=np.concatenate(parts.edge_kinds),
        blocks=blocks,
        bounds=np.stack([faces.reshape(-1, 3).min(0), faces.reshape(-1, 3).max(0)]),
    )
    logger.debug("building: %d blocks, %d faces, %d edges", len(blocks), len(faces), len(building.edges))
    return building
