"""``Tracker``: live tracking, one frame at a time, in an incremental GTSAM graph (iSAM2).

Each ``step``: predict the pose (the odometry given with the frame, else constant velocity, scaled by the
timestamps when given); refine it on the map lines visible near the prediction (``sequence.refine_from``:
the fix checks); add the frame to iSAM2 with its line-projection factor and a ``BetweenFactorPose3`` (the
odometry with its covariance, or the constant-velocity model with ``velocity_sigma_*``); read the pose and
its marginal covariance back. A frame failing the checks is a loss: with odometry it gets the predicted
pose from the graph (``success=False``, reason "from neighbours ..."); a relocalization then runs, near the
prediction (a ``Prior``), or after ``global_after_frames`` lost frames without odometry in the ball the
camera can have reached since its last fix (``max_speed_m_s`` and timestamps given), else globally. A
relocalization near a prediction that odometry made joins the graph as a tracked fix does (odometry factor,
innovation gate); any other restarts the graph at its pose. The graph is re-anchored every ``window``
frames (a prior with the newest pose's covariance), so memory stays flat.
A fix many sigmas from its prediction (the chi-square innovation gate, ``SequenceConfig.gate_probability``)
enters the graph but is not claimed: ``success=False``, reason "from neighbours and its lines ..."; so does
a fix on a track whose last ``consistency_window`` fixes together lie beyond the gate over them. A fix
refined from a guess (a prediction without odometry, or after a lost frame) must also pass the global
decision's rival tests (``sequence.rival_test``: the fix turned and orbited, then moved along its valley);
a fix from odometry skips the tests (their cost) but is moved along its valley too (``sequence.valley_move``:
a track refined from a prediction already off settles in the nearest basin); every fix then meets its
prediction refined at the fine distance and becomes it when that is the same answer and sharper
(``sequence.prediction_move``: a refinement from a prediction on the truth can slide to a neighbouring
basin that scores more at 4 px and fits less closely); one refused for a rival is
relocalized near its prediction at once; when that cannot decide either, without odometry the fix joins
the graph unclaimed (event tracked, reason "ambiguous ... the track follows it") rather than leaving the
track to the constant-velocity guess. A relocalization not near a prediction (global, or in the ball the
camera can have reached), and a fix refined from a prediction ``global_after_frames`` lost frames old
without odometry, starts a track that is posed but not claimed ("unconfirmed ...") until an
independent relocalization of a later frame lands on it (``confirm_global``): one frame's answer can be a
repeated structure's twin, or what scores best where the search missed the truth. Frames coasting on
odometry gather in a window; once odometry no longer holds the window rigid to within the score's resolution,
the window is turned to where its frames' summed score is best (``align.align_window``) and that rotation
enters the graph as a measurement of the newest pose (``align.rotation_prior``); the frames stay unclaimed.
``event`` says what the last step did: initialized, tracked, relocalized, predicted, lost.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from .align import align_window, rotation_prior
from .camera import Camera
from .errors import InvalidInputError
from .geometry import camera_center, check_rigid
from .graph import (
    LineFit,
    chi2_quantile,
    frame_key,
    frame_lines,
    from_pose3,
    innovation_distance,
    line_fit,
    next_tolerance,
    noise_px,
    odometry_factor,
    predict,
    relative_pose,
    step_covariance,
    to_pose3,
)
from .localization import localize_segments
from .map.linemap import LineMap
from .pipeline import differs, with_map_floor
from .priors import Prior
from .registration import Registration
from .score import ImageLines, image_lines
from .sequence import (
    AMBIGUOUS,
    FROM_NEIGHBOURS,
    SequenceConfig,
    prediction_move,
    refine_from,
    relocalize,
    rival_test,
    valley_move,
    visible_mask,
)

log = logging.getLogger(__name__)


def _tracking_sequence() -> SequenceConfig:
    """The sequence checks with a refinement sized for a good prediction: fewer rounds and iterations, and
    the residuals' noise by their MAD (``RefineConfig.noise_model``: the fix tests were measured with it)."""
    base = SequenceConfig()
    refine = replace(
        base.register.refine, max_rounds=3, max_iterations=10, start_factor=1.5, noise_model="mad"
    )
    return replace(base, register=replace(base.register, refine=refine))


@dataclass(frozen=True)
class TrackingConfig:
    """Live tracking: the per-frame checks and odometry defaults (``sequence``), the motion model, the window."""

    sequence: SequenceConfig = field(default_factory=_tracking_sequence)
    # the constant-velocity model between frames without odometry: sigma per frame
    velocity_sigma_rot_deg: float = 3.0
    velocity_sigma_pos_m: float = 0.15
    window: int = 50  # frames in the iSAM2 graph before it is re-anchored at the newest pose
    # a refined frame explaining less than this share of what the last 5 fixes explained is not a fix
    min_explained_ratio: float = 0.6
    # a global relocalization (no prior: the first frame without ``start_at``, or after
    # ``global_after_frames`` lost frames without odometry) decides on one frame, and on repeated structure
    # (the courtyard's 180-degree twin, a facade one bay over) a wrong pose can win it clearly. Its track is
    # posed but not claimed until a global relocalization of a later frame (every ``relocalize_every``
    # tracked frames), independent of the track, lands on it (``pipeline.differs`` says no); one landing
    # elsewhere replaces the track, unconfirmed too. False: a global relocalization is claimed at once.
    confirm_global: bool = True
    # the camera's top speed (m/s; None: unknown). Without odometry, after ``global_after_frames`` lost
    # frames, a relocalization then searches only the ball the camera can have reached since its last fix
    # (``relocalize_radius_m`` + speed x the time since, from the frames' timestamps), at any rotation, and
    # is confirmed as a global one is, by a later frame's relocalization in the ball it can then have reached
    # (no prediction ties it to the track, and a search that misses the truth in the ball claims whatever
    # scores best there: on the synthetic walk a facade copy 3.2 m off whose truth scored 4 % more): a copy
    # of the scene beyond that reach (the courtyard's twin) cannot be the answer. Without timestamps, or once
    # the ball holds the whole map, it is global.
    max_speed_m_s: float | None = None
    relinearize_threshold: float = 0.01
    # the innovation gate over the last this many fixes of a track (their summed squared Mahalanobis
    # distances, each at most the per-frame gate's, against the chi-square quantile of 6 x as many degrees
    # of freedom at the sequence's ``gate_probability``): a track whose fixes keep landing off its
    # predictions has left its frames' lines, or its covariance is optimistic, and a fix on it is not
    # claimed even when it alone passes the gate (the synthetic walk of seed 3: a track orbiting off the
    # truth along a facade claimed 6 frames 0.30-0.41 m off between fixes gated at 5-23 sigma); 0: the
    # per-frame gate only
    consistency_window: int = 5
    # window alignment of coasting frames (``align``): at most this many of the window's frames are scored
    # (evenly spread; cost only: a window's frames see much the same); 0: no window alignment
    align_frames: int = 6


class Tracker:
    """Tracks one camera through a line map, frame by frame (``step``)."""

    def __init__(self, line_map: LineMap, camera: Camera, config: TrackingConfig | None = None):
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"camera must be a linereg.Camera, got {type(camera).__name__}")
        self.line_map = line_map
        self.camera = camera
        self.config = config or TrackingConfig()
        speed = self.config.max_speed_m_s
        if speed is not None and not (math.isfinite(speed) and speed > 0):
            raise InvalidInputError(
                f"TrackingConfig.max_speed_m_s must be a positive number or None, got {speed}"
            )
        self._cam = camera.undistorted()
        self.event = "none"
        self.frames = 0  # frames stepped
        self.alignments = 0  # window alignments entered in the graph
        self._reset()

    def _reset(self) -> None:
        self._isam: gtsam.ISAM2 | None = None
        self._keys = 0  # frames in the current graph
        self._k = -1  # the newest frame's index in the graph
        self._pose: np.ndarray | None = None  # the newest cam_from_world
        self._velocity: np.ndarray | None = None  # cam_k-1_from_cam_k of the last two fixes
        self._stamp: float | None = None
        self._dt: float | None = None
        self._lost = 0
        self._explained: list[float] = []  # explained shares of the last fixes
        self._innovations: list[float] = []  # squared Mahalanobis distances of the track's last fixes
        self._unconfirmed: int | None = None  # frames since an unconfirmed global relocalization, or None
        self._fix: tuple[float, np.ndarray] | None = None  # (timestamp, centre) of the last claimed fix
        self._clear_window()

    def _clear_window(self) -> None:
        self._window: list[tuple[ImageLines, np.ndarray]] = []  # coasted frames since the last evidence
        self._window_var = 0.0  # rotation variance per axis (rad^2) odometry added over the window

    def start_at(
        self, cam_from_world: np.ndarray, sigma_rot_deg: float = 1.0, sigma_pos_m: float = 0.05
    ) -> None:
        """Starts (or restarts) tracking from a known (4, 4) pose with the given uncertainty."""
        pose = check_rigid(cam_from_world, "cam_from_world")
        self._anchor(pose, np.diag([np.radians(sigma_rot_deg) ** 2] * 3 + [sigma_pos_m**2] * 3))
        self._unconfirmed = None
        self.event = "initialized"

    @property
    def cam_from_world(self) -> np.ndarray | None:
        """(4, 4) the newest pose, or None before the first fix."""
        return self._pose

    def step(
        self, frame: np.ndarray, relative_pose: np.ndarray | None = None, timestamp: float | None = None
    ) -> Registration:
        """Returns the Registration of the next frame: an image of the camera's size or (N, 4) segments.

        relative_pose: measured (4, 4) cam_prev_from_cam_this (odometry since the previous frame);
        timestamp: seconds, increasing. Bad input raises InvalidInputError and leaves the tracker as it was.
        """
        start = time.perf_counter()
        relative = None if relative_pose is None else check_rigid(relative_pose, "relative_pose")
        if timestamp is not None and not (
            math.isfinite(timestamp) and (self._stamp is None or timestamp > self._stamp)
        ):
            raise InvalidInputError(
                f"timestamp must be finite and increasing, got {timestamp} after {self._stamp}"
            )
        lines = frame_lines(frame, self.camera, self.config.sequence.detect)
        self.frames += 1
        image = image_lines(lines, self._cam, self.config.sequence.register.score)
        result = self._step(lines, image, relative, timestamp)
        if timestamp is not None:
            self._dt = None if self._stamp is None else timestamp - self._stamp
            self._stamp = timestamp
        return replace(result, timings={**result.timings, "step": time.perf_counter() - start})

    def _step(
        self, lines: np.ndarray, image: ImageLines, relative: np.ndarray | None, stamp: float | None
    ) -> Registration:
        cfg = self.config.sequence
        predicted, step, cov = self._predict(relative, stamp)
        radius = cfg.max_relocalize_radius_m
        tracked = Registration(success=False, reason="no pose yet")
        # without odometry, after global_after_frames lost frames the prediction no longer places the search
        untrusted = relative is None and self._lost >= cfg.global_after_frames
        enough = len(lines) >= cfg.register.min_lines2d
        if not enough:  # no fix can come of it: not refined (nor culled for)
            tracked = Registration(
                success=False, reason=f"{len(lines)} line segments (< {cfg.register.min_lines2d})"
            )
        elif predicted is not None and self._pose is not None:
            radius = min(cfg.relocalize_radius_m * (1 + self._lost), cfg.max_relocalize_radius_m)
            # without odometry the motion is a guess: standing still competes with constant velocity
            starts = [predicted] if relative is not None else [predicted, self._pose]
            # a prediction without odometry, or after lost frames, is a guess: its fix is a local search
            tracked = self._track(image, starts, radius, guessed=relative is None or self._lost > 0)
            if tracked.success and untrusted:
                return self._restart(image, tracked, stamp)
            if tracked.success:
                self.event = "tracked"
                return self._join(lines, image, tracked, predicted, step, cov, stamp)
        self._lost += 1
        # a fix refused for its rivals is a frame the search near the prediction must decide, at once
        rivalled = tracked.reason.startswith(AMBIGUOUS)
        if enough and (rivalled or (self._lost - 1) % cfg.relocalize_every == 0):
            near = predicted if self._lost <= cfg.global_after_frames or relative is not None else None
            ball = self._reach(stamp) if near is None else None
            found = self._relocalize(lines, image, near, radius, ball)
            if found.success and near is not None and relative is not None:
                # odometry links this frame to the track: the fix joins its graph as a tracked one does
                # (gated, weighed against the odometry) instead of restarting it at one frame's answer
                self.event = "relocalized"
                return self._join(lines, image, found, near, step, cov, stamp)
            if found.success:
                self.event = "initialized" if self._pose is None else "relocalized"
                previous, consecutive = self._pose, self._lost == 1
                self._start(image, found, independent=near is None)
                if previous is not None and consecutive:  # the motion since the last frame is known
                    self._velocity = relative_pose(previous, found.cam_from_world)
                if self._unconfirmed is not None:
                    return replace(found, success=False, reason=self._unconfirmed_reason())
                return self._claimed(found, stamp)
        if rivalled and untrusted:
            return self._restart(image, tracked, stamp)
        if rivalled and relative is None:
            # an ambiguous fix (an orbit along a facade's valley, a turn on clutter, scores as much) that the
            # search near the prediction could not decide either still pins the pose to that neighbourhood,
            # and the track's motion picks its side: followed, not claimed. A track that set such frames
            # aside coasted on the constant-velocity guess, which carries the last turn on and on (on the
            # synthetic walks, 20-100 degrees off after a few seconds) until a global relocalization found
            # it again. With odometry the frame coasts on the odometry, which holds the track better (a
            # walk's track following ambiguous fixes slid 0.45 m along a valley and claimed 10 frames there).
            assert predicted is not None
            self.event = "tracked"
            return self._join(lines, image, tracked, predicted, step, cov, stamp, claim=False)
        # only odometry holds coasting frames together (a constant-velocity guess does not): a window
        return self._coast(image if relative is not None else None, tracked, predicted, step, cov)

    def _join(
        self,
        lines: np.ndarray,
        image: ImageLines,
        fix: Registration,
        predicted: np.ndarray,
        step: np.ndarray | None,
        cov: np.ndarray | None,
        stamp: float | None,
        claim: bool = True,
    ) -> Registration:
        """Returns the Registration of a fix added to the track's graph with the motion from its
        predecessor: claimed unless the innovation gate doubts it or its track is unconfirmed. ``claim``
        False: a fix refused as ambiguous that the track follows (``_step``), never claimed."""
        doubt = self._doubt(fix, predicted, step, cov)
        added = self._add(image, fix, step, cov)
        doubt = self._confirm(lines, image, added, stamp) or doubt
        if not claim:
            return replace(added, success=False, reason=f"{fix.reason}; the track follows it, not claimed")
        return replace(added, success=False, reason=doubt) if doubt else self._claimed(added, stamp)

    def _restart(self, image: ImageLines, fix: Registration, stamp: float | None) -> Registration:
        """Returns the Registration of a fix refined from a prediction the tracker no longer trusts: without
        odometry after ``global_after_frames`` lost frames, when its relocalizations search globally. Such a
        fix is one frame's answer, found from a guess metres and tens of degrees off (a constant velocity
        carried through the loss), and checked only against rivals near it: like a global relocalization it
        starts a new track, unconfirmed (``confirm_global``). (On the synthetic walk of seed 0, a fix after
        28 lost frames landed on a facade copy 7.4 m off, passed the rival test, and its track claimed 23
        frames.)"""
        self.event = "relocalized"
        self._start(image, fix, independent=True)
        if self._unconfirmed is not None:
            reason = self._unconfirmed_reason() if fix.success else fix.reason
            return replace(fix, success=False, reason=reason)
        return self._claimed(fix, stamp) if fix.success else fix

    def _claimed(self, result: Registration, stamp: float | None) -> Registration:
        """Returns a claimed fix, noting when and where it was (the reach of ``max_speed_m_s``)."""
        if stamp is not None:
            self._fix = (stamp, camera_center(result.cam_from_world))
        return result

    def _reach(self, stamp: float | None) -> tuple[np.ndarray, float] | None:
        """Returns ((3,) centre, radius m) of the ball the camera can have reached since its last claimed
        fix at ``max_speed_m_s``, or None (no speed, timestamps or fix; or a ball holding the whole map)."""
        speed = self.config.max_speed_m_s
        if speed is None or stamp is None or self._fix is None:
            return None
        when, centre = self._fix
        radius = self.config.sequence.relocalize_radius_m + speed * max(stamp - when, 0.0)
        ends = self.line_map.segments.reshape(-1, 3)
        far = float(
            np.linalg.norm(np.maximum(np.abs(ends.min(axis=0) - centre), np.abs(ends.max(axis=0) - centre)))
        )
        return None if radius >= far else (centre, radius)

    def _relocalize(
        self,
        lines: np.ndarray,
        image: ImageLines,
        near: np.ndarray | None,
        radius: float,
        ball: tuple[np.ndarray, float] | None = None,
    ) -> Registration:
        """Returns the Registration of (N, 4) undistorted segments (``image``: their ``image_lines``),
        registered near ``near``, else in a ``ball`` ((3,) centre, radius m) at any rotation, else globally."""
        start = time.perf_counter()
        if near is None and ball is not None:
            prior = Prior(position=ball[0], radius_m=ball[1])
            found = localize_segments(lines, self.line_map, self._cam, self.config.sequence.register, prior)
        else:
            found = relocalize(lines, self.line_map, self._cam, near, radius, self.config.sequence, image)
        return replace(found, timings={**found.timings, "relocalize": time.perf_counter() - start})

    def _confirm(self, lines: np.ndarray, image: ImageLines, added: Registration, stamp: float | None) -> str:
        """Returns why a tracked frame is not claimed because its track is unconfirmed ("" when it is
        confirmed, now or before): every ``relocalize_every`` frames of an unconfirmed track, the frame is
        also relocalized independently of the track (in the ball the camera can have reached since its last
        claimed fix, else globally); a pose the decision calls the same answer as the track's confirms it, a
        distinct one replaces the track (unconfirmed: one frame's answer against another's)."""
        if self._unconfirmed is None:
            return ""
        self._unconfirmed += 1
        cfg = self.config.sequence
        if self._unconfirmed % cfg.relocalize_every == 0 and len(lines) >= cfg.register.min_lines2d:
            found = self._relocalize(lines, image, None, cfg.max_relocalize_radius_m, self._reach(stamp))
            if found.success:
                T = added.cam_from_world
                if not differs(found.cam_from_world, T, self.line_map.segments, cfg.register.decide):
                    self._unconfirmed = None
                    return ""
                log.info("tracking: a relocalization contradicts the unconfirmed track; restarting")
                self._start(image, found, independent=True)
        return self._unconfirmed_reason()

    def _unconfirmed_reason(self) -> str:
        return (
            f"unconfirmed: relocalized apart from the track {self._unconfirmed} frame(s) ago; not claimed until "
            "an independent relocalization of a later frame lands on the same track"
        )

    def _track(
        self, image: ImageLines, starts: list[np.ndarray], radius: float, guessed: bool
    ) -> Registration:
        """Returns the best-scoring refinement from the start poses; a fix only if it also explains at
        least ``min_explained_ratio`` of what the recent fixes explained (a wrong basin explains less) and,
        refined from a ``guessed`` prediction, passes the global decision's turn test."""
        cfg = self.config
        tried = [refine_from(image, self.line_map, self._cam, T, radius, cfg.sequence) for T in starts]
        best = max(tried, key=lambda r: (r.success, r.score))
        if best.success and self._explained:
            usual = float(np.median(self._explained))
            if best.explained_fraction < cfg.min_explained_ratio * usual:
                reason = f"tracking: explains {100 * best.explained_fraction:.0f} % of the lines, the recent frames {100 * usual:.0f} %"
                return replace(best, success=False, reason=reason)
        if best.success and guessed:
            best = rival_test(image, self.line_map, self._cam, best, self.config.sequence)
        elif best.success:  # with odometry no rival test (its cost), but the fix moves along its valley
            # (the synthetic walks with odometry: 1 -> 0 wrong claims, 1,003 -> 1,111 of 1,280 frames within)
            best = valley_move(image, self.line_map, self._cam, best, self.config.sequence)
        if best.success:  # the prediction refined at the fine distance, if it is the same answer and sharper
            best = prediction_move(image, self.line_map, self._cam, best, starts[0], self.config.sequence)
        if best.success:
            self._explained = [*self._explained[-4:], best.explained_fraction]
        return best

    def _doubt(
        self, tracked: Registration, predicted: np.ndarray, step: np.ndarray | None, cov: np.ndarray | None
    ) -> str:
        """Returns why a fix is not claimed ("" when it is): its pose lies farther from the prediction than
        ``gate_probability`` of the predicted distribution allows (the chi-square innovation gate), or the
        track's last ``consistency_window`` fixes, this one included (noted here), lie beyond the gate over
        them. The fix still enters the graph (refusing it outright strands the tracker when the covariances
        are optimistic); the frame is reported with the graph's pose, ``success=False``."""
        p = self.config.sequence.gate_probability
        if not p or step is None or cov is None:
            return ""
        d2 = innovation_distance(
            predicted, tracked.cam_from_world, self._covariance(), step, cov, tracked.covariance
        )
        limit = chi2_quantile(p, 6)
        n = self.config.consistency_window
        # a fix beyond the gate counts as one at the gate: one lying odometry step is not a track astray
        self._innovations = [*self._innovations, min(d2, limit)][-n:] if n else []
        if d2 > limit:
            return (
                f"{FROM_NEIGHBOURS} and its lines: its own fix is {math.sqrt(d2):.1f} sigma from the "
                f"prediction (gate {math.sqrt(limit):.1f} sigma), so it is not claimed"
            )
        if not n:
            return ""
        total, window = sum(self._innovations), chi2_quantile(p, 6 * len(self._innovations))
        if total <= window:
            return ""
        return (
            f"{FROM_NEIGHBOURS} and its lines: the track's last {len(self._innovations)} fixes lie "
            f"{math.sqrt(total):.1f} sigma from their predictions (gate {math.sqrt(window):.1f} sigma): the track "
            "disagrees with its frames' lines, so it is not claimed"
        )

    def _predict(
        self, relative: np.ndarray | None, stamp: float | None
    ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """Returns (predicted pose, cam_prev_from_cam_this step, its (6, 6) covariance), Nones before a fix."""
        if self._pose is None:
            return None, None, None
        cfg = self.config
        if relative is not None:
            sc = cfg.sequence
            return (
                predict(self._pose, relative),
                relative,
                step_covariance(
                    relative, sc.odometry_rot_deg_per_m, sc.odometry_pos_fraction, sc.odometry_floor_m
                ),
            )
        step = np.eye(4) if self._velocity is None else self._velocity
        if self._velocity is not None and stamp is not None and self._stamp is not None and self._dt:
            xi = gtsam.Pose3.Logmap(gtsam.Pose3(step)) * ((stamp - self._stamp) / self._dt)
            step = gtsam.Pose3.Expmap(xi).matrix()
        cov = np.diag([np.radians(cfg.velocity_sigma_rot_deg) ** 2] * 3 + [cfg.velocity_sigma_pos_m**2] * 3)
        return predict(self._pose, step), step, cov * (1 + self._lost) ** 2

    def _start(self, image: ImageLines, found: Registration, independent: bool) -> None:
        """Starts a new graph at a relocalized pose: a prior with its covariance and its line factor. A
        global (``independent``) relocalization starts an unconfirmed track (``confirm_global``); one near
        the prediction keeps the track's standing."""
        cov = found.covariance if np.isfinite(found.covariance).all() else np.diag([1e-4] * 3 + [1e-2] * 3)
        self._anchor(found.cam_from_world, cov)
        if independent and self.config.confirm_global:
            self._unconfirmed = 0

    def _anchor(self, cam_from_world: np.ndarray, covariance: np.ndarray) -> None:
        """Starts a new graph: a prior at a (4, 4) pose with its (6, 6) covariance."""
        self._reset_graph()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        key = frame_key(self._k + 1)
        noise = gtsam.noiseModel.Gaussian.Covariance(covariance)
        graph.add(gtsam.PriorFactorPose3(key, to_pose3(cam_from_world), noise))
        values.insert(key, to_pose3(cam_from_world))
        self._update(graph, values)
        self._velocity, self._lost = None, 0
        self._innovations = []
        self._clear_window()

    def _reset_graph(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        self._isam = gtsam.ISAM2(params)
        self._keys = 0

    def _add(
        self, image: ImageLines, tracked: Registration, step: np.ndarray | None, cov: np.ndarray | None
    ) -> Registration:
        """Adds a tracked frame to iSAM2 (line factor + motion factor); returns its Registration."""
        sc = self.config.sequence
        previous = self._pose
        if self._keys >= self.config.window:
            self._reanchor()
        key = frame_key(self._k + 1)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(key, to_pose3(tracked.cam_from_world))
        rc = sc.register
        fit = self._fit(key, image, tracked.cam_from_world, rc.score.distance_px, 1.0)
        if fit is not None:  # again at the fit's own tolerance and noise level
            r = fit.residuals(tracked.cam_from_world)
            fit = self._fit(
                key, image, tracked.cam_from_world, next_tolerance(r, rc), noise_px(r, rc, sc.min_noise_px)
            )
        if fit is None or step is None or cov is None:
            return tracked  # cannot happen for a tracked frame (it has a prediction and matches)
        graph.add(fit.factor)
        graph.add(odometry_factor(self._k, step, cov))
        self._update(graph, values)
        assert previous is not None and self._pose is not None
        self._velocity, self._lost = relative_pose(previous, self._pose), 0
        self._clear_window()
        seen = self.line_map.segments[tracked.matches[:, 1]]
        return replace(tracked, cam_from_world=self._pose, covariance=self._reported(seen))

    def _fit(
        self, key: int, image: ImageLines, pose: np.ndarray, tolerance_px: float, sigma_px: float
    ) -> LineFit | None:
        cfg = self.config.sequence.register
        return line_fit(key, image, self.line_map.segments, self._cam, pose, tolerance_px, sigma_px, cfg)

    def _coast(
        self,
        image: ImageLines | None,
        tracked: Registration,
        predicted: np.ndarray | None,
        step: np.ndarray | None,
        cov: np.ndarray | None,
    ) -> Registration:
        """Returns the Registration of a lost frame: the graph's prediction when there is one. ``image``:
        the frame's lines when odometry moved it (it joins the window of coasting frames), else None."""
        if predicted is None or step is None or cov is None or self._isam is None:
            self.event = "lost"
            return replace(tracked, success=False, reason=f"lost: {tracked.reason}")
        self.event = "predicted"
        key = frame_key(self._k + 1)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(key, to_pose3(predicted))
        graph.add(odometry_factor(self._k, step, cov))
        self._update(graph, values)
        reason = f"{FROM_NEIGHBOURS}: {self._lost} frame(s) predicted since the last fix ({tracked.reason})"
        reason += self._coasted(image, cov)
        assert self._pose is not None
        return Registration(
            success=False,
            reason=reason,
            cam_from_world=self._pose,
            covariance=self._reported(np.zeros((0, 6))),
            timings=tracked.timings,
        )

    def _coasted(self, image: ImageLines | None, step_cov: np.ndarray) -> str:
        """Returns what the window alignment did ("" when it did not run): the coasted frame joins the
        window; once the rotation variance odometry added over the window exceeds the score's resolution
        (``distance_px`` as an angle: the window is no longer rigid at the scale the score sees), the
        window is aligned within the innovation gate of the newest pose's rotation and starts again."""
        cfg = self.config
        if not cfg.align_frames or image is None:
            self._clear_window()
            return ""
        rc = cfg.sequence.register
        if self._window:  # the motion between the window's frames (not the step into its first)
            self._window_var += float(np.trace(step_cov[:3, :3])) / 3.0
        if len(image.segments) >= rc.min_lines2d:
            assert self._pose is not None
            self._window.append((image, self._pose))
        resolution = rc.score.distance_px / max(self._cam.fx, self._cam.fy)
        if self._window_var <= resolution**2:
            return ""
        window = self._window
        self._clear_window()
        sigma = float(np.sqrt(np.max(np.diag(self._covariance())[:3])))
        if not window or not np.isfinite(sigma):
            return ""
        gate_p = cfg.sequence.gate_probability
        gate = math.sqrt(chi2_quantile(gate_p, 3)) if gate_p else 3.0
        pick = np.unique(np.linspace(0, len(window) - 1, cfg.align_frames).round().astype(int))
        visible = visible_mask(self.line_map, camera_center(window[-1][1]), cfg.sequence.relocalize_radius_m)
        found = align_window(
            [window[i][0] for i in pick], [window[i][1] for i in pick], self.line_map.segments, self._cam,
            max(gate * sigma, 2.0 * resolution), resolution, rc, visible,
        )  # fmt: skip
        if found is None:
            return ""
        assert self._pose is not None
        graph = gtsam.NonlinearFactorGraph()
        graph.add(rotation_prior(frame_key(self._k), self._pose, found))
        self._update_only(graph)
        self.alignments += 1
        turn = math.degrees(float(np.linalg.norm(found.rotation)))
        spread = math.degrees(math.sqrt(float(np.trace(found.covariance))))
        return f"; the last {len(window)} frames' summed score turned them {turn:.1f} deg (+-{spread:.1f})"

    def _update_only(self, graph: gtsam.NonlinearFactorGraph) -> None:
        """Adds factors on existing frames to iSAM2 and reads the newest pose back."""
        assert self._isam is not None
        self._isam.update(graph, gtsam.Values())
        self._pose = from_pose3(self._isam.calculateEstimatePose3(frame_key(self._k)))

    def _reanchor(self) -> None:
        """Restarts iSAM2 with a prior at the newest pose and its marginal covariance (bounded memory)."""
        assert self._pose is not None
        cov = self._covariance()
        self._reset_graph()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        key = frame_key(self._k)
        graph.add(
            gtsam.PriorFactorPose3(key, to_pose3(self._pose), gtsam.noiseModel.Gaussian.Covariance(cov))
        )
        values.insert(key, to_pose3(self._pose))
        self._isam.update(graph, values)  # type: ignore[union-attr]
        self._keys = 1

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        assert self._isam is not None
        self._isam.update(graph, values)
        self._k += 1
        self._keys += 1
        self._pose = from_pose3(self._isam.calculateEstimatePose3(frame_key(self._k)))

    def _reported(self, seen: np.ndarray) -> np.ndarray:
        """Returns the newest frame's covariance as reported: the graph's marginal (what the innovation
        gate uses: consecutive frames share the map's error) plus what the map's own accuracy adds, seeing
        the (K, 6) world segments ``seen`` (``pipeline.with_map_floor``)."""
        assert self._pose is not None
        return with_map_floor(self._covariance(), self.line_map.accuracy_m, seen, self._pose)

    def _covariance(self) -> np.ndarray:
        assert self._isam is not None
        try:
            return np.asarray(self._isam.marginalCovariance(frame_key(self._k)))
        except RuntimeError:
            return np.full((6, 6), np.nan)

    def centre(self) -> np.ndarray | None:
        """Returns the (3,) newest camera centre, or None before the first fix."""
        return None if self._pose is None else camera_center(self._pose)
