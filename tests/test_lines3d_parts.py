"""The stages of lines3d.extract on known answers: raster contours, edge refinement, direction families,
rectangle candidates, collinear merging."""

from dataclasses import replace

import numpy as np
import pytest

from linereg.config import Lines3DConfig
from linereg.map.collinear import merge_collinear
from linereg.map.contours import image_contours, image_lines
from linereg.map.edge_refine import refine_edges
from linereg.map.line_families import box_lines, dominant_directions, snap_to_families

BASIS = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # a facade y = const: u along x, v up
VERTICAL = (np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), np.array([50.0, 40.0]))  # families: z, x
CONFIG = Lines3DConfig()


def _angle_deg(lines: np.ndarray) -> np.ndarray:
    d = lines[:, 2:] - lines[:, :2]
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0


def test_image_lines_of_a_rectangle_with_a_hole():
    image = np.zeros((60, 80), np.uint8)
    image[10:50, 10:70] = 255
    image[20:35, 30:45] = 0  # a window
    contours, hole = image_contours(image)
    assert hole.sum() == 1 and len(contours) == 2
    lines = image_lines(image, contours, 5.0, Lines3DConfig())
    assert len(lines) == 8  # 4 sides outside, 4 round the hole
    angles = _angle_deg(lines)
    assert np.all(np.minimum(angles % 90.0, 90.0 - angles % 90.0) < 1.0)  # axis-aligned
    xs = lines[np.isclose(angles % 180.0, 90.0, atol=1.0), 0]
    for x in (10, 69, 29, 45):  # outer sides on the outermost pixels, the hole's on its neighbours
        assert np.abs(xs - x).min() <= 1.0


def test_refine_moves_a_raster_line_onto_the_edge():
    rng = np.random.default_rng(0)
    uv = rng.uniform([0.0, 0.0], [4.0, 3.0], size=(12_000, 2))  # spacing ~3 cm, edge u = 4
    lines = np.array([[3.9, 0.5, 3.9, 2.5]])  # a raster line 10 cm inside
    out, kept = refine_edges(uv, lines, 0.15, CONFIG, fixed=np.array([True]))
    assert kept.all()
    assert out[0, 0] == pytest.approx(4.0, abs=0.01) and out[0, 2] == pytest.approx(4.0, abs=0.01)


def test_refine_drops_a_line_where_the_surface_goes_on():
    rng = np.random.default_rng(1)
    uv = rng.uniform([0.0, 0.0], [4.0, 3.0], size=(12_000, 2))
    region, beyond = uv[uv[:, 0] < 3.0], uv[uv[:, 0] >= 3.0]  # labels stop at u = 3, the plane does not
    lines = np.array([[3.0, 0.5, 3.0, 2.5]])
    _, kept = refine_edges(region, lines, 0.15, CONFIG, fixed=np.array([True]))
    assert kept.all()
    beside = np.c_[beyond, np.zeros(len(beyond))]  # unlabelled points in the plane
    _, kept = refine_edges(region, lines, 0.15, CONFIG, beside, np.array([True]))
    assert not kept.any()
    tolerant = replace(CONFIG, edge_max_going_on=1e9)  # the config's limit decides, not a constant
    _, kept = refine_edges(region, lines, 0.15, tolerant, beside, np.array([True]))
    assert kept.all()


def test_families_and_snapping():
    rng = np.random.default_rng(2)
    z = np.c_[rng.uniform(0, 10, (20, 2)), np.zeros(20)]
    vertical = np.c_[z, z[:, :2], rng.uniform(1, 3, 20)]  # 20 vertical segments
    horizontal = np.array([[0, 0, h, 5, 0, h] for h in range(5)], dtype=np.float64)
    dirs, support = dominant_directions(np.concatenate([vertical, horizontal]), CONFIG)
    assert len(dirs) == 2
    assert np.abs(dirs @ [0, 0, 1.0]).max() == pytest.approx(1.0)
    tilted = np.array([[1.0, 0.0, 1.0 + np.tan(np.radians(6.0)), 1.0]])  # 6 degrees off vertical (v up)
    snapped, fixed = snap_to_families(tilted, BASIS, (dirs, support), CONFIG)
    assert fixed.all()
    assert snapped[0, 0] == pytest.approx(snapped[0, 2])  # vertical now, turned about its midpoint
    assert 0.5 * (snapped[0, 0] + snapped[0, 2]) == pytest.approx(0.5 * (1.0 + tilted[0, 2]))


def test_box_lines_of_a_rectangle_not_of_a_circle():
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]])
    sides = box_lines([square], BASIS, VERTICAL, CONFIG)
    assert len(sides) == 4
    assert sorted(np.round(np.linalg.norm(sides[:, 2:] - sides[:, :2], axis=1), 6)) == [1, 1, 2, 2]
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    circle = np.c_[np.cos(t), np.sin(t)]
    assert len(box_lines([circle], BASIS, VERTICAL, CONFIG)) == 0  # fills pi / 4 of its box
    assert len(box_lines([circle], BASIS, VERTICAL, CONFIG, min_fill=0.0)) == 4  # a point set: any shape
    loose = replace(CONFIG, rectangle_min_fill=0.75)
    assert len(box_lines([circle], BASIS, VERTICAL, loose)) == 4


def test_merge_collinear_matches_pairwise_rule():
    config = Lines3DConfig()
    pieces = np.array(
        [
            [0, 0, 0, 1, 0, 0],
            [1.1, 0.02, 0, 2, 0.02, 0],  # within 4 cm, 10 cm gap: joins
            [2.5, 0, 0, 3, 0, 0],  # 50 cm gap: stays apart
            [0, 0.1, 0, 1, 0.1, 0],  # 10 cm beside: stays apart
            [0, 0, 0, 0, 1, 0],  # another direction
        ],
        dtype=np.float64,
    )
    merged = merge_collinear(pieces, np.zeros(len(pieces)), config)
    lengths = np.sort(np.round(np.linalg.norm(merged[:, 3:] - merged[:, :3], axis=1), 2))
    assert lengths.tolist() == [0.5, 1.0, 1.0, 2.0]
