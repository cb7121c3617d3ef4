"""Configuration of colorization: one frozen section per stage, the defaults documented where they are set."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..config import override


@dataclass(frozen=True)
class SurfaceConfig:
    """Local point spacing and surface normal of every point, from point statistics in voxels."""

    # voxel edge (m) of the statistics; 0 = 8 x the cloud's typical spacing (~64 points on a planar patch)
    voxel_m: float = 0.0
    # a voxel holding fewer points takes its statistics from the voxel 4x as large round it
    min_points: int = 6


@dataclass(frozen=True)
class VisibilityConfig:
    """A depth buffer per photo from the cloud itself: point splats, then a depth test with a tolerance."""

    # splat diameter = this x the local spacing (projected): 1 closes the gaps between neighbouring points
    splat_scale: float = 1.0
    # splats are squares of 2^L pixels; L stops here (nearer points than that may leave gaps)
    max_splat_px: int = 16
    near_m: float = 0.1  # points nearer to a camera are not seen by it
    # a point is visible when it lies at most this far behind the buffer's depth: a floor (scan noise,
    # ~3 sigma of 1 cm) and the depth change across what the buffer cannot resolve on a slanted surface
    # (from the normal; it grows with range as the pixel's footprint does). No share of the range by
    # default: the buffer is made of the same points seen from the same pose, so a pose or calibration
    # error moves a point and its own splat together; 0.004 of the range let points 0.1-0.3 m behind a
    # window reveal through at 20-50 m. Raise it for clouds whose scans disagree (misregistration).
    depth_tol_m: float = 0.04
    depth_tol_rel: float = 0.0
    # the slope term of the tolerance stops at this tan(incidence): a surface seen more grazing than
    # atan(max_slope) hides parts of itself rather than let what lies behind an occluder through
    max_slope: float = 1.5
    # the depth test covers the pixels within half the point's splat diameter (``depth.footprint_radius_px``:
    # an occluder's outline lies up to half a spacing beyond its splats) and at least this many round its
    # pixel: a point beside an occluder's silhouette is not coloured (its photo colour there mixes both
    # surfaces anyway: bilinear sampling, optical blur), nor one whose splat overlaps an occluder's
    silhouette_margin_px: int = 1
    # the depth test allows this many pixels of the surface's slope (``depth.tolerance_m``): a neighbour's
    # splat is tilted by its own voxel's normal (a few degrees off on a noisy or sparse surface) from
    # its point, up to half a pixel from the pixel centre the test meets it at; 0 leaves slanted
    # surfaces at range hiding parts of themselves
    slope_slack_px: float = 0.5
    # gap closing after the splats (``depth.fill_gaps``): a pixel that meets a nearer surface in at least
    # ``gap_directions`` of 8 directions within ``gap_radius_px`` lies in a hole of that surface (irregular
    # and striped sampling leaves holes up to ~5 px wide); 6 keeps a pixel beside a straight edge (3-5)
    gap_radius_px: int = 3
    gap_directions: int = 6
    gap_passes: int = 3  # a pass closes a hole enclosed on 6 sides; holes of odd shapes take more


@dataclass(frozen=True)
class WeightConfig:
    """Weight of a photo's colour at a point: viewing angle, range, image border, blur."""

    min_cos: float = 0.15  # surfaces seen more grazing than acos(0.15) = 81 degrees take no colour
    angle_power: float = 1.0  # weight ~ cos(angle between the viewing ray and the normal) ^ power
    range_power: float = 2.0  # weight ~ 1 / range ^ power (the pixel footprint on the surface)
    border_px: float = 16.0  # the weight ramps from 0 at the image border to 1 this far inside
    blur_power: float = 2.0  # weight ~ (sharpness / sharpest photo's) ^ power
    # the blend raises the product to this power: > 1 favours the best photo (sharper, less ghosting)
    blend_power: float = 2.0


@dataclass(frozen=True)
class GainConfig:
    """Exposure / white balance: one gain per photo and channel, from points several photos see."""

    enabled: bool = True
    sample_points: int = 200_000  # points of the cloud (evenly strided) the gains are estimated on
    iterations: int = 30
    dark: int = 8  # colour values below (noise) or above 255 - dark (clipped) are not used
    max_gain: float = 4.0  # gains are clipped to [1 / max_gain, max_gain]
    # weight of the prior "gain = 1" of each photo, in observations (of weight 1, the best photo's)
    prior_points: float = 500.0
    # only surfaces seen within acos(min_cos) = 60 degrees of head-on, away from depth edges, count
    min_cos: float = 0.5


@dataclass(frozen=True)
class ColorizeConfig:
    """Everything ``colorize`` can be told; ``ColorizeConfig.from_dict`` overrides nested per section."""

    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    weights: WeightConfig = field(default_factory=WeightConfig)
    gains: GainConfig = field(default_factory=GainConfig)
    # points processed at once (memory: ~100 bytes per point, plus every photo's depth buffer)
    chunk_points: int = 1_000_000

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ColorizeConfig:
        """Returns the default config with the keys of ``d`` (nested per section) overridden."""
        return override(cls(), d, "config")
