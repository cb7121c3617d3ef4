"""Every tunable of the pipeline: one frozen dataclass per stage, defaults documented in code.

Defaults follow the paper (section III) where it gives a value; the rest are ours and say why.
Override with ``dataclasses.replace``, ``RegisterConfig.from_dict`` or a JSON file of overrides
(``io.read_config``; the CLI's ``--config FILE``). One default configuration serves the API, the CLI and
the service.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any, Literal

from .errors import InvalidInputError


@dataclass(frozen=True)
class Lines3DConfig:
    """3D line segments from a point cloud: planar regions, their contours and creases (Lu et al. 2019)."""

    downsample_m: float = 0.0  # optional voxel downsampling before anything else; 0 = keep every point
    voxel_m: float = 0.1  # cube of the local plane fits (normals by PCA) that regions grow over
    scales: int = 4  # points left over are grown again with voxels 2, 4, 8 x voxel_m (sparse, far surfaces)
    min_voxel_points: int = 5  # fewer points cannot fix a plane
    max_curvature: float = 0.03  # lambda_min / sum(lambda) above this: the voxel straddles a crease
    angle_deg: float = 10.0  # neighbouring voxel normals closer than this grow one region
    distance_m: float = 0.03  # point-to-plane distance that still belongs to a region
    merge_angle_deg: float = 5.0  # adjacent regions this parallel ...
    merge_distance_m: float = 0.05  # ... and this close to each other's plane are one
    min_region_points: int = 60
    min_region_area_m2: float = 0.1  # smaller regions (clutter) give neither contours nor creases
    cell_m: float = 0.0  # raster cell of a region's contour; 0 = cell_spacings x the region's point spacing
    cell_spacings: float = 1.5  # a little coarser than the sampling: few empty cells (false holes) inside
    # a spinning LiDAR's rings lie range x this angle apart (set by ``map.profile`` with the sensor origin):
    # a region's raster cell is at least that x its range, else its raster falls apart between rings
    ring_cell_deg: float = 0.0
    # rasters are coarsened beyond this many pixels, to bound memory (a 6 km^2 plane in 1 cm cells: 6e10)
    max_raster_pixels: int = 40_000_000
    approx_cells: float = 1.5  # polygon approximation tolerance of a contour (cells)
    # contour lines this close to a region's dominant direction take it (a raster staircase, one cell in 9,
    # tilts a line 6 degrees); 0 = off
    snap_angle_deg: float = 10.0
    # global direction families below this share of the best one's length are chance directions (raster
    # diagonals, clutter): which of them exist is a matter of rounding, and no line should take theirs
    family_min_share: float = 0.05
    family_in_plane_deg: float = 3.0  # a family this close to a region's plane is one of its directions
    # a contour line is kept if lines sharing its direction hold this share of the region's line length, or
    # if it is lone_fraction of the region's longer side: a ragged outline's chords go every way, each short
    dominant_share: float = 0.15
    lone_fraction: float = 0.25
    beside_depth_m: float = 0.3  # points of no region this far off a plane may bound it (reveals, ledges)
    # edge refinement: a raster line tilted more than this to fit the points has no straight edge behind it
    edge_max_tilt_deg: float = 10.0
    edge_min_line_points: int = 10  # fewer points along a line: the raster's closing bridged a gap
    edge_min_bin_points: int = 6  # the outermost of fewer points in a bin says little about the edge
    # a point this much inside a bin's outermost lies on the scan's next row (nearer: same row, range noise)
    edge_row_step_m: float = 0.015
    edge_on_plane_m: float = 0.01  # points of no region this close to a region's plane lie on it (noise)
    # this many such points beyond an edge (share of the region's points along it): the surface goes on,
    # only its labels stop (region growing leaves out the points round a crease), so no edge
    edge_max_going_on: float = 0.2
    min_length_m: float = 0.3  # shorter segments are dropped
    crease_min_angle_deg: float = 20.0  # planes meeting at a larger angle give an intersection line
    # a crease bounds both regions: this share of each one's points near it lie on one side (a rough
    # surface's facets crossing mid-way have points on both sides)
    crease_one_sided: float = 0.8
    collinear_angle_deg: float = 2.0  # segments this parallel ...
    collinear_distance_m: float = 0.04  # ... this close to one line ...
    collinear_gap_m: float = 0.15  # ... and this close along it are merged
    # candidates: midpoints within 2 collinear_distance_m plus this across their direction group's axis,
    # room for segments tilted within the angle
    collinear_slack_m: float = 0.1
    # sides of the direction-aligned rectangles round each region and its rectangular holes are candidate
    # edges too (window panes, ledge strips, window holes span too few raster cells for their contours):
    # off, as the extra true edges come with edges that mislead localization (docs/measurements.md)
    rectangles: bool = False
    rectangle_min_fill: float = 0.85  # a contour filling this share of its bounding rectangle is a rectangle


@dataclass(frozen=True)
class MapProfileConfig:
    """What kind of cloud it is and the map-building parameters that follow (``map.profile``): a dense
    RGB-D room shows furniture-scale faces and edges that the building-scale defaults drop; a spinning
    LiDAR's rings lie a range-proportional gap apart, which a region's raster must bridge."""

    spacing_sample: int = 20_000  # points whose nearest-neighbour distances estimate the spacing s
    length_spacings: float = 12.0  # shortest segment 12 s ...
    min_length_range_m: tuple[float, float] = (0.15, 0.3)  # ... clipped to this (upper end: the default)
    area_spacings: float = 15.0  # smallest region (15 s)^2: some 15 points a side give straight contours ...
    min_area_range_m2: tuple[float, float] = (0.03, 0.1)  # ... clipped to this (upper end: the default)
    # plane-fit voxels of voxel_spacings x s (enough points to fit, small enough for a shelf board),
    # clipped to this range (upper end: the default)
    voxel_spacings: float = 6.0
    voxel_range_m: tuple[float, float] = (0.05, 0.1)
    # a cloud whose 8th nearest neighbours lie this many x farther at the 90th than at the 10th
    # percentile was sampled from a point (a scanner: density falls with range), not voxelised, fused or
    # thinned into an even density (the nearest neighbour's distance alone spreads 4-5x on any cloud thinned
    # at random, the 8th's 1.6x)
    uneven_ratio: float = 4.0
    density_neighbours: int = 8
    dense_spacing_m: float = 0.025  # an even cloud this dense is an RGB-D fusion (a room); coarser: a map
    # scan rings: consecutive points (scan order) this close in azimuth belong to one ring ...
    ring_step_deg: float = 2.0
    min_ring_points: int = 100  # ... rings are runs of at least this many points ...
    min_ring_span_deg: float = 45.0  # ... turning this far in azimuth (a cropped sweep: the camera's view)
    min_rings: int = 8  # ... and a sweep has at least this many ...
    # ... and at most this many (128 lasers, each split where its turn crosses the back): a fused cloud
    # stored in grid order has hundreds of runs; else rings by quantised elevation:
    max_rings: int = 300
    elevation_bin_deg: float = 0.05  # the histogram of elevations whose peaks are the lasers' cones
    elevation_peak_share: float = 0.8  # this share of the points beyond a metre lies on the cones ...
    cone_share: float = 0.3  # ... each within this share of the gap between cones of one
    cone_rounds: int = 10  # at most this many moves of the sensor origin to where the cones are sharpest ...
    max_origin_shift_m: float = 1.0  # ... and no farther from where the rings were looked for about
    # a ring field's sensor origin: fitted to its cones from the frame's origin raised by each of these (m),
    # in at most this many steps (``rings_from_field``)
    field_heights_m: tuple[float, ...] = (0.0, 1.0, 2.0)
    field_rounds: int = 40
    field_sharp_deg: float = 0.1  # ... the next height tried only when the fit leaves a larger rms error
    field_reach_m: float = 10.0  # ... the sensor within this of the frame's origin in each axis
    # a region's raster cell is at least this share of the ring gap at its range (the closing bridges one
    # empty cell between rings)
    ring_cell_share: float = 0.6
    # points sampled to estimate the noise: the rms distance to the plane of their 16 nearest neighbours
    noise_sample: int = 2000
    noise_distances: float = 3.0  # a region holds points within this many noise rms of its plane ...
    distance_range_m: tuple[float, float] = (0.03, 0.08)  # ... clipped to this (lower end: the default)


@dataclass(frozen=True)
class PlaneDirectionsConfig:
    """Map directions from the dominant planes (``map.plane_directions``): normals and crease directions."""

    normal_angle_deg: float = 3.0  # region normals this close are one plane direction (fits to many points)
    min_area_share: float = 0.03  # a plane direction holds at least this share of the planar area
    max_planes: int = 6  # dominant plane directions considered (6 give 15 creases)
    # planes meeting at a smaller angle give no reliable crease: n_a x n_b amplifies errors by 1 / sin
    crease_min_angle_deg: float = 20.0
    in_plane_deg: float = 3.0  # a direction this close to a plane's surface lies in it
    # a dominant plane this close to perpendicular to the frame's reference plane is one of its walls
    # (fused RGB-D rooms: walls 1-2 degrees off the floor's perpendicular)
    perpendicular_deg: float = 5.0
    max_regions: int = 2000  # only the largest regions vote: they hold the area; the (R, R) test stays small
    # plane directions rank before clusters of segments alone: a real cloud's clutter (far-range depth
    # noise) holds more segment length than its walls' edges, and its segments lean by degrees
    planes_first: bool = True


@dataclass(frozen=True)
class VisibilityConfig:
    """Which map segments a camera sees (``map.visibility``): frustum, occlusion by the map's surfaces."""

    sample_px: float = 3.0  # a segment is ray-cast at samples this far apart in the image
    max_samples: int = 4000  # ... at most this many per segment (a segment across a 4K image)
    min_depth_m: float = 0.05  # points nearer than this to the camera plane are not seen
    # a sample is hidden when a surface lies this much nearer than it along its ray: segments lying ON a
    # surface (the map's own boundaries and creases) must not hide themselves, and the mesh is
    # rasterised (a cell off) and the range noisier far away
    depth_tolerance_m: float = 0.05
    depth_tolerance_fraction: float = 0.02  # ... plus this fraction of the sample's range
    # potentially-visible sets: cells of this size (m; 0 = the map's largest extent / 16, at least 0.5 m)
    pvs_cell_m: float = 0.0
    pvs_piece_m: float = 0.25  # segments are cut into pieces this long; a piece hidden by one occluder
    pvs_max_occluders: int = 400  # the largest surface rectangles tested as occluders (the rest: no culling)
    pvs_margin_m: float = 0.02  # an occluder must lie this clear of the box and of the piece it hides


@dataclass(frozen=True)
class SensorEdgesConfig:
    """Edges seen from the sensor of a single sweep (``map.sensor_edges``): depth discontinuities and
    sharp bends along the scan rings of a spinning LiDAR."""

    # a neighbour along the ring this much farther (fraction of the range, plus jump_m) is behind an
    # occluding contour: the nearer point is on the silhouette
    jump_fraction: float = 0.1
    jump_m: float = 0.3
    # LOAM's smoothness: |sum of the 2 w neighbours' range differences| / (2 w range) above this is a bend
    window: int = 5
    bend: float = 0.08
    # edge points of neighbouring rings join one edge when within this many ring gaps of each other ...
    link_gaps: float = 1.6
    max_link_m: float = 1.5  # ... and no farther than this
    line_tolerance_fraction: float = 0.012  # a point belongs to a line within this fraction of its range
    min_points: int = 4  # points of one edge (at least as many rings cross it)
    min_length_m: float = 0.3  # shorter edges are dropped
    min_ring_points: int = 50  # a ring with fewer points gives no edges
    along_plane_m: float = 0.1  # an edge this close along a plane's boundary or crease is that line


@dataclass(frozen=True)
class IntensityEdgesConfig:
    """Steps of a single sweep's intensity along its scan rings (``map.intensity_edges``): road markings,
    paint, signs; lines through them are linked and fitted as ``SensorEdgesConfig`` says."""

    window: int = 2  # points averaged on each side of a gap along the ring
    contrast: float = 0.3  # a step of at least this share of the sweep's 5-95 % intensity range ...
    noise_sigmas: float = 4.0  # ... and this many of its own noise (returns scatter along a ring)
    # neighbours whose ranges differ by more than this share are on different surfaces: no step between
    max_range_step_fraction: float = 0.05


@dataclass(frozen=True)
class PointEdgesConfig:
    """Edges of an evenly sampled cloud found per point (``map.point_edges``): where the surface bends or
    ends, then grouped into lines along the scene's directions (small structure: furniture, frames)."""

    neighbours: int = 20  # nearest points of each point's normal (PCA) and of its boundary test
    compare_neighbours: int = 16  # nearest points whose normals a point's is compared with
    # this share of the compared neighbours' normals crease_deg from a point's: the surface bends there (a
    # crease's band); one turned neighbour is noise (a fused room's normals scatter by 10-20 degrees)
    crease_deg: float = 30.0
    bend_share: float = 0.25
    # the neighbours' centroid this far (share of their radius) off the point, in its tangent plane: the
    # surface ends on one side (a boundary); a full disc has its centroid at its centre, a half disc 0.42
    boundary_shift: float = 0.3
    # edge points projected along a direction pile up where a line of that direction runs: the
    # projection's histogram (cells one spacing wide) is smoothed by a Gaussian of smooth_cells, and a
    # pile is the largest within peak_cells around it (a 3 cm post's four corners stay four piles) ...
    smooth_cells: float = 0.7
    peak_cells: int = 1
    width_spacings: float = 1.5  # ... points within this many spacings of a pile's centre belong to it ...
    gap_spacings: float = 5.0  # ... and split into runs where this many spacings along it hold no point
    fill: float = 0.5  # a run holds at least this many points per spacing of its length
    direction_deg: float = 5.0  # directions of the scene this close are one
    # a run whose cross-section (every point within section_spacings of it) is one flat sheet through it
    # (thinner than flat_noises x the cloud's noise or flat_aspect x its width, its centroid within
    # centred_share of the radius from the run) lies inside a surface: no edge
    section_spacings: float = 5.0
    flat_noises: float = 2.0
    flat_aspect: float = 0.35
    centred_share: float = 0.3
    along_m: float = 0.03  # an edge this close along a plane's boundary or crease is that line
    chunk: int = 200_000  # points per batch of neighbour fits (memory: chunk x neighbours x 3 floats)


@dataclass(frozen=True)
class MapBuildConfig:
    """Everything ``LineMap.build`` needs, one section per stage of map building."""

    lines3d: Lines3DConfig = field(default_factory=Lines3DConfig)
    profile: MapProfileConfig = field(default_factory=MapProfileConfig)
    sensor: SensorEdgesConfig = field(default_factory=SensorEdgesConfig)
    point: PointEdgesConfig = field(default_factory=PointEdgesConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    # choose the cloud-dependent fields of ``lines3d`` from the cloud (``map.profile``); fields set to
    # other values than their defaults are kept as given
    adapt: bool = True
    sensor_edges: bool = True  # occluding contours and ring edges where the sensor origin is known
    # steps of the intensity along a single sweep's rings (``map.intensity_edges``), when the cloud has an
    # intensity per point: off by default (the paper's maps are untextured)
    intensity_edges: bool = False
    intensity: IntensityEdgesConfig = field(default_factory=IntensityEdgesConfig)
    # edges found per point (``map.point_edges``); None: for dense RGB-D fusions (``build.POINT_EDGE_KINDS``),
    # whose points have round neighbourhoods a few cm across; a scanner's rings and range falloff do not
    point_edges: bool | None = None
    surfaces: bool = True  # keep the planar regions as a mesh (occlusion-aware visibility)
    mesh_cell_m: float = 0.1  # the surface mesh's cells are at least this (and the region's raster cell)
    # the direction clusters take the directions of the dominant planes (``map.plane_directions``)
    plane_directions: bool = True
    directions: PlaneDirectionsConfig = field(default_factory=PlaneDirectionsConfig)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> MapBuildConfig:
        """Returns the default config with the keys of ``d`` (nested per section) overridden."""
        return override(cls(), d, "config")


@dataclass(frozen=True)
class VanishingConfig:
    """2D vanishing directions by multiple RANSAC on interpretation-plane normals (Rother 2002)."""

    num_clusters: int = 5  # paper: c = 5 clusters before merging
    inlier_angle_deg: float = 1.5  # a segment belongs to a VD if it points within this angle of the VP
    # endpoint noise (px, std): a segment of length L also gets 2*sqrt(2)*noise_px/L rad of angular slack,
    # so short segments (whose direction is uncertain) are judged fairly without loosening long ones
    noise_px: float = 2.0
    merge_angle_deg: float = 5.0  # VDs closer than this are one (paper: merge near-duplicates)
    ransac_iterations: int = 200
    # random segments each hypothesis is scored on (all when fewer): the best stands out on a sample too
    score_sample: int = 800
    min_lines: int = 3  # smaller clusters are not a direction
    top_k: int = 3  # paper: "the former two or three"
    seed: int = 0


@dataclass(frozen=True)
class ParallelConfig:
    """3D parallel clusters by RANSAC on segment directions."""

    num_clusters: int = 5  # paper: c = 5
    parallel_angle_deg: float = 1.0  # paper: 1 degree for 3D parallel lines
    # endpoint noise (m, std) of extracted map segments: a segment of length L also gets 2*sqrt(2)*noise_m/L
    # rad of angular slack (real clouds give short segments whose directions are off by degrees, which the
    # fixed 1 degree leaves unclustered), capped at max_angle_deg; 0 = the paper's fixed 1 degree
    noise_m: float = 0.02
    max_angle_deg: float = 8.0
    # as for VDs: with the noise slack, one real direction can come out as two clusters a few degrees apart
    merge_angle_deg: float = 5.0
    ransac_iterations: int = 100
    # random segments each hypothesis is scored on (all when fewer): 1000 estimate a cluster's share of the
    # length to ~1.5 % (binomial std), all that choosing the best needs
    score_sample: int = 1000
    min_lines: int = 3
    top_k: int = 3
    seed: int = 0


@dataclass(frozen=True)
class RotationConfig:
    """Rotation candidates from VD <-> 3D direction pairings."""

    # angle(VD1, VD2) must match angle(D1, D2) within this; VDs of a few dozen short, noisy segments are off
    # by degrees (their distance from the image is poorly fixed), so a tight tolerance rejects true pairings
    pair_angle_tolerance_deg: float = 8.0
    third_pair_tolerance_deg: float = 8.0  # a third pair validates a candidate within this (same reason)
    dedupe_angle_deg: float = 1.0  # candidates closer than this are one
    min_pair_angle_deg: float = 10.0  # directions closer than this to (anti)parallel cannot fix a rotation
    top_k: int = 3  # pairings are tried among the strongest top_k VDs and top_k 3D clusters
    max_candidates: int = 24
    # "separate": image share of the paired VDs + map share of the paired clusters, the angles decide which
    # goes with which; "product": sum of sqrt(VD share x cluster share) (strongest with strongest)
    ranking: Literal["separate", "product"] = "separate"
    # when a third pair confirms some candidates, this many others follow them (0: only the confirmed; a
    # spurious confirmation then leaves only wrong ones); each costs a translation screening
    max_unconfirmed: int = 8
    refit: bool = True  # re-fit each candidate's R to the member segments of its paired VDs, not the VDs
    # one matched direction leaves an angle about it: scored by the image segments the other map directions
    # explain within this (``free_angle_scores``) ...
    single_tolerance_deg: float = 4.0
    single_min_share: float = 0.5  # ... the angles of local maxima scoring this share of the best are tried


@dataclass(frozen=True)
class ScoreConfig:
    """The score of a pose (``score.py``): image line length the visible map explains, less what it predicts
    in empty image areas."""

    # a projected map line covers an image segment where it runs within this of the segment's line (both
    # ends of the shared stretch) ...
    distance_px: float = 4.0
    angle_deg: float = 4.0  # ... at an angle below this (LSD's angle on a 30 px segment is good to ~2 deg)
    # where the image has no segment within this fraction of its diagonal it shows no line at all (sky,
    # blank walls): map lines predicted there count against the pose
    empty_radius_fraction: float = 0.08
    unexplained_weight: float = 1.0
    min_depth_m: float = 0.05  # map points nearer than this to the camera plane are not scored


@dataclass(frozen=True)
class PointsConfig:
    """Corners and free segment ends (``points.py``), the image and map points the search votes with."""

    gap_px: float = 6.0  # an image segment's end this close to a crossing (+ gap_fraction of it) joins it
    gap_fraction: float = 0.15  # ... a fraction of the segment's length (LSD shortens segments at corners)
    min_angle_deg: float = 20.0  # lines closer to parallel than this make no corner
    line_gap: float = 0.5  # 3D lines must pass within this fraction of the gap of each other to meet
    corner_weight: float = 2.0  # a corner pins a camera ray better than a free end (two directions)


@dataclass(frozen=True)
class SearchConfig:
    """The search over camera centres (``search.py``): rays from matched points vote in a voxel grid."""

    # the search region is cut into about this many cubic voxels for coarse votes (4 x 32 MB per voting
    # thread, mapped lazily: what the rays reach, ~1-2 % of the voxels, is resident): at 2 M (1.7 m
    # voxels on the demo's 60 m block) shifts of a window lattice outvoted the true camera centre, whose
    # coarse peak was then never solved (docs/measurements.md)
    voxels: int = 8_000_000
    coarse_peaks: int = 8  # ... the best of each rotation are voted again on a finer grid:
    fine_voxels: int = 16  # ... of this many voxels a side
    fine_span: float = 3.0  # ... spanning this many coarse voxels each way
    # a ray votes only farther than this many coarse voxels from its map point: near a map point the rays
    # of every image point matched to it and to its neighbours cross whatever the camera is, and every
    # top peak of a cluttered room's votes lay at a map point (docs/measurements.md); a voxel also counts
    # each map point once, as it counts each image point once (a camera centre is a matching)
    min_range_voxels: float = 6.0
    # an image point and a map point may correspond when both arms agree within this under the rotation
    # (vanishing directions are good to a few degrees, and so is a candidate rotation)
    arm_angle_deg: float = 8.0
    # a map arm seen from farther than this x focal x its length / the image arm's length would look too
    # short to make the image arm (a fragment may be shorter than its map line, not many times longer)
    arm_length_ratio: float = 2.0
    # each fine peak is solved quickly: this many of ``solve_rounds``' rounds, the tolerance halving from
    # one spanning its voxel and the rotation's error. One round misranks some true peaks (a crossroad
    # photo's: 92nd of 381); three measured mixed across the benches (docs/measurements.md, session 40)
    quick_rounds: int = 1
    peaks: int = 16  # the fine peaks scoring best after their quick solves are solved fully
    # with a map's surfaces, the fine peaks' quick solves are scored with what they hide while what they
    # explain unhidden (nearly a bound: ``search.screen``) reaches this fraction of the best so far
    screen_fraction: float = 0.7
    # a rotation candidate from vanishing directions is off by up to about this: scoring and solving a peak
    # start at a tolerance that covers it
    rotation_slack_deg: float = 1.0
    # with a prior, only the map segments that can project at least this long into the image from a pose it
    # allows are searched (``map.reach``): a shorter one explains or contradicts at most that many pixels
    min_projected_px: float = 2.0
    # rotations are voted in up to this many threads (as OpenCV may use: service workers one), each holding its
    # own grids (2 x 64 MB per region): the same peaks on any count
    max_threads: int = 4
    solve_rounds: int = 6  # local solve: match at a shrinking tolerance, re-solve the pose
    # without a prior the camera centres searched are the map's box grown by each of these fractions of its
    # largest extent on every side, each box voted on its own grid: fine near the map (photos of a mapped
    # building are taken from outside it), coarse far out (a small mapped object seen from afar)
    region_margins: tuple[float, ...] = (1.0, 2.5)


@dataclass(frozen=True)
class DecideConfig:
    """When is the best pose an answer (``pipeline.decide``): clearly better than every distinct rival."""

    # a pose clearly distinct from the best (rotation, or camera centre farther than distinct_fraction of the
    # scene depth) scoring above (1 - margin) x best makes the answer ambiguous, unless what the best
    # explains beyond it passes the significance test below on its own and what it explains beyond the
    # best does not (``pipeline.advantage_nfa`` both ways)
    margin: float = 0.15
    distinct_angle_deg: float = 2.0
    distinct_fraction: float = 0.05
    # the best pose's number of false alarms (significance.py): how many of the poses searched would match as
    # many image segments by chance; an answer needs log10 of it below this (0: fewer than one, the
    # a-contrario rule)
    max_log10_nfa: float = 0.0
    # ... and explain at least this fraction of the image's line length lying where the map could explain it
    # at that pose (near its surfaces or its visible lines: ``pipeline.explains_too_little``; also a tracked
    # frame's fix test): the chance model assumes independent segments, and on the real kitchen sequence a
    # wrong global pose explaining under it passed the significance test alone (docs/measurements.md)
    min_explained_fraction: float = 0.15
    contenders: int = 4  # the best distinct poses of the search are refined before deciding
    # the best pose turned (pan, tilt) beyond distinct_angle_deg, moving its projection up to this fraction
    # of the image diagonal, is a rival too: where the image's clutter lets a displaced copy of the map
    # explain nearly as much, the alignment is chance, whether or not the search found the true pose
    turn_reach_fraction: float = 0.06
    # an image segment is matched to the map segment covering most of it, if that covers more than this
    # fraction of it (the paper's overlap test)
    min_cover: float = 0.5
    # copies of the best pose's matched corners elsewhere in the map (``copies.py``), under each rotation
    # searched: where corners holding this share of them agree on a camera centre (copies sharing fewer are
    # left to the search); each is scored where it stands, and this many, the best by what the surfaces hide
    # from them (``search.screen``), are solved and are rivals
    copy_share: float = 0.4
    copies: int = 16
    # ... and so is the best pose orbited by these angles (up, down, left, right) round the point at its
    # median depth ahead, solved from there: the slope of the valley where a turn and a shift compensate
    orbit_deg: tuple[float, ...] = (3.0, 6.0)
    # a rival within the margin is told apart at a tolerance this fraction of the score's distance where the
    # best keeps at least ``sharp_keep`` of its score (its lines lie that close: the map is accurate there)
    # and the rival scores below (1 - margin) of the best: a turn of 3 deg round a facade 20 m away keeps
    # its lines within 4 px but not within 1 (measured on the demo, docs/measurements.md, session 25)
    sharp_fraction: float = 0.25
    sharp_keep: float = 0.5
    # an answer's covariance holds the spread of the basins next to it within the margin and not distinct,
    # solved from it turned by this angle each way about each camera axis (``pipeline.near_basins``; 0: none)
    basin_turn_deg: float = 1.0


@dataclass(frozen=True)
class RefineConfig:
    """GTSAM refinement on fragments (``refine.py``): the matched stretch of each map line onto its image
    line, robust kernel, re-associate at each refined pose."""

    kernel: Literal["huber", "cauchy", "tukey", "none"] = "huber"  # per scalar residual (gtsam Scalar scheme)
    kernel_px: float = 2.0
    # re-association keeps covers within outlier_sigmas sigmas of the residuals' noise, at least
    # min_outlier_px and at most the last round's tolerance: the test tightens as the pose converges. The
    # noise: "mixture", the inliers' sigma in a mixture with outliers spread evenly over the last round's
    # tolerance (``refine.inlier_sigma``); "mad", 1.4826 x the residuals' median (the pairs of a wide first
    # round hold so many outliers that it is theirs, and it kept the tolerance wide). The tracker keeps the
    # MAD: its fix tests were measured with it, and with the mixture three tracked frames of a synthetic
    # walk were claimed 0.3 m off (docs/measurements.md, session 49)
    noise_model: Literal["mixture", "mad"] = "mixture"
    outlier_sigmas: float = 3.0
    min_outlier_px: float = 2.0
    start_factor: float = 2.5  # the first round covers at this many times the score's tolerance
    min_cover_px: float = 5.0  # shorter covered stretches carry no direction: left out of the fit
    max_rounds: int = 5  # optimise -> re-associate rounds
    max_iterations: int = 50  # Levenberg-Marquardt iterations per round
    relative_error_tol: float = 1e-5  # LM stops when the cost drops by less than this fraction
    min_matches: int = 4  # fewer covered stretches than this (3 is minimal for 6 DoF) are not refined
    parallel_angle_deg: float = 2.0  # all matched 3D lines within this of one direction: degenerate
    min_depth_m: float = 1e-3  # points nearer than this (or behind the camera) are clamped to it


@dataclass(frozen=True)
class LineDetectConfig:
    """2D segments: OpenCV LSD, then merging of collinear fragments and removal of short isolated ones."""

    lsd_scale: float = 0.7  # LSD's Gaussian subsampling (OpenCV default 0.8): lower: faster, fewer fragments
    max_work_pixels: int = 600_000  # bigger images are subsampled further: LSD sees at most this many pixels
    # LSD runs on this many overlapping bands of the image (merging rejoins segments cut at a band's edge),
    # in parallel threads when OpenCV may use them (cv2.getNumThreads() > 1), else one after the other; a
    # fixed count, so that an image gives the same segments on any machine, in a worker or not
    lsd_bands: int = 2
    # px of LSD's subsampled image a band reaches into its neighbours: a line cut at a band's edge keeps a
    # piece longer than LSD's smallest region in each band, or lies whole in one band
    lsd_band_overlap_px: float = 12.0
    merge_angle_deg: float = 3.0  # fragments whose directions differ by more are not one line
    merge_offset_px: float = 1.5  # every fragment endpoint must lie within this of the merged line
    merge_gap_frac: float = 0.02  # largest gap bridged, fraction of the image diagonal (paper: 60 px)
    max_merge_rounds: int = 10  # merging repeats until stable or this many rounds
    min_length_frac: float = 0.025  # shorter segments left after merging are dropped (paper: 80 px)
    # LSD segments this close (px) to the picture's border, or to a flat frame round it, and this parallel
    # to it are the picture's end, not the scene's; 0 = keep them
    border_px: float = 3.0
    border_angle_deg: float = 5.0


@dataclass(frozen=True)
class RegisterConfig:
    """Everything ``register`` needs, one section per stage."""

    min_lines2d: int = 6
    min_lines3d: int = 6
    min_inliers: int = 6  # fewer matched image segments than this is not a pose
    vanishing: VanishingConfig = field(default_factory=VanishingConfig)
    parallel: ParallelConfig = field(default_factory=ParallelConfig)
    rotation: RotationConfig = field(default_factory=RotationConfig)
    score: ScoreConfig = field(default_factory=ScoreConfig)
    points: PointsConfig = field(default_factory=PointsConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    decide: DecideConfig = field(default_factory=DecideConfig)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RegisterConfig:
        """Returns the default config with the keys of ``d`` (nested per section) overridden."""
        return override(cls(), d, "config")


def override(obj: Any, d: dict[str, Any], path: str) -> Any:
    """Returns the frozen dataclass ``obj`` with the keys of ``d`` replaced, nested dataclasses recursively;
    an unknown key or a non-mapping raises InvalidInputError naming it by ``path`` (``config.score.nope``)."""
    if not isinstance(d, dict):
        raise InvalidInputError(f"{path} must be a mapping, got {type(d).__name__}")
    known = {f.name: f for f in fields(obj)}
    changes = {}
    for key, value in d.items():
        if key not in known:
            raise InvalidInputError(f"unknown option {path}.{key}; known: {', '.join(known)}")
        current = getattr(obj, key)
        changes[key] = override(current, value, f"{path}.{key}") if is_dataclass(current) else value
    return replace(obj, **changes)
