"""Settings of the localizer (:class:`LocalizeConfig`) and of its success checks (:class:`SuccessChecks`).

Fields left None follow the map (what its build asks for, ``localize_defaults`` in its provenance) or the
extractor's policy (:class:`favormap.features.ExtractorPolicy`). The measurements behind the defaults are
in docs/implementation-notes.md ("Localization")."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import InputError
from ..view_limits import ViewLimits


def _localizer_view_limits() -> ViewLimits:
    """Landmarks are tried from up to 60 deg beyond their training view cone and 0.25-4x their training
    distances."""
    return ViewLimits(angle_margin_deg=60.0, depth_scale=(0.25, 4.0))


@dataclass
class SuccessChecks:
    """What a pose must satisfy to be reported as a success."""

    min_inliers: int = 20
    # inliers / matches of the final iteration: at views extrapolated from the mapping path most mutual matches
    # are wrong and correct poses have 12-20 % inliers; an image of another scene gets ~3 %
    min_inlier_ratio: float = 0.1
    max_iteration_change: tuple[float, float] = (0.05, 2.0)  # last two estimates: (x median landmark depth, deg)
    min_visible_inliers: float = 0.8  # share of inlier landmarks visible from the final pose
    # A pose with fewer inliers than this must be confirmed by the prior-free step (the query matched
    # against all landmarks' mean descriptors, Lowe's test, PnP): confirm_min_inliers of its matches lie within
    # the RANSAC threshold of the pose, or its estimate exists and lies within max_iteration_change of the pose
    # (refined from a prior) / the pose stayed that close to it (refined from that estimate). This refuses poses
    # that a repeated pattern lines up (keypoints on one copy matched to landmarks on another). 0: never ask.
    confirm_below_inliers: int = 100
    # The prior-free step confirms with this many inliers (of its estimate, or of the pose among its matches), fewer
    # than a pose to report needs (min_inliers): it only has to agree with the refined pose, which is the evidence.
    # 12: the structure baseline's success threshold. 0: only a prior-free estimate of min_inliers confirms.
    confirm_min_inliers: int = 12


@dataclass
class LocalizeConfig:
    """Settings of :class:`favormap.localize.Localizer`."""

    iterations: int = 3  # rendering iterations at most (render -> match -> PnP from the last estimate)
    # cosine similarity of descriptor matching and (unless guided_match_threshold) of the guided step;
    # None: the extractor's (ExtractorPolicy.match_threshold)
    match_threshold: float | None = None
    mutual: bool = True  # also require the landmark to be the query feature's best
    ratio: float = 1.0  # Lowe ratio on descriptor distances in the rendering iterations (1: off)
    global_ratio: float | None = None  # Lowe ratio when matching against all landmarks (None: the extractor's)
    max_keypoints: int = 4096  # query keypoints
    # PnP-RANSAC threshold, at the working resolution of the map (max_side). None: the map's (ransac_threshold):
    # min_ransac_px, or pose_noise_ransac times the map's epipolar limit where its mapping poses fit the images
    # less well than that
    ransac_max_error_px: float | None = None
    min_ransac_px: float = 4.0
    pose_noise_ransac: float = 1.5
    # a rendering iteration's RANSAC estimate is then refined on the matches within this many pixels of it,
    # where checks.min_inliers lie that close (its inliers stay those within the RANSAC threshold); None: off
    fit_max_error_px: float | None = 4.0
    checks: SuccessChecks = field(default_factory=SuccessChecks)
    # The guided step, after the rendering iterations (search by projection): every landmark visible from the
    # estimate is matched to the most similar query keypoint within guided_radius_px of its projection and within
    # guided_gate_sigma standard deviations (Mahalanobis) of it under the weighted refinement's noise model,
    # mutually and above the threshold; then PnP-RANSAC at guided_ransac_px (None: the radius). 0: off.
    guided_radius_px: float = 8.0
    guided_ransac_px: float | None = None
    guided_gate_sigma: float = 3.0  # 0: the radius alone
    # the guided step runs only for poses with fewer inliers matched by descriptor (None: every pose): with many,
    # the pose is at its noise floor already and matches chosen near the predicted projections add noise
    guided_below_inliers: int | None = 400
    guided_rounds: int = 1  # > 1: search again from the previous round's (weighted) pose
    guided_match_threshold: float | None = None  # cosine threshold of the guided step (None: match_threshold)
    # The final pose is refined once more on its inliers, each residual weighted by how well its landmark is
    # known (favormap.localize.refine: position covariance from the training views' spread and distance for a
    # keypoint noise of the mapping images, projected into the query, plus keypoint_sigma_px of query keypoint
    # noise). That mapping noise in pixels, "map" (one figure for the map: the median of its landmarks') or
    # "landmark" (each landmark's own, from its reprojection errors); 0: RANSAC's refinement only.
    landmark_sigma_px: float | str = "landmark"
    keypoint_sigma_px: float = 0.5  # query keypoint noise (px) of that refinement
    # the noise model of that refinement: "fixed" (the map's landmark covariances and keypoint_sigma_px as they
    # are) or "estimated" (both scaled to this query's inliers by maximum likelihood,
    # favormap.localize.refine.estimate_noise): far from the mapping path the covariances understate the depth
    # errors several times
    refine_noise: str = "estimated"
    # before that refinement, each inlier's keypoint is moved to where its landmark's appearance in the mapping
    # frame nearest in direction, carried through the landmark's local plane, lies in the query
    # (favormap.localize.align; needs the map's stored patches or the mapping images: align_images, or None for
    # the folder the map was built from). None: the map's choice (mapfile.model.map_aligns_by_default)
    align: bool | None = None
    align_images: str | None = None
    align_references: int = 1  # mapping frames each inlier is aligned to (AlignConfig.references)
    global_fallback: bool = True  # no prior, or the prior failed: coarse pose from all landmarks' mean descriptors
    global_max_landmarks: int = 200_000  # longest-track landmarks searched without a prior
    # the least inliers of that coarse pose for the rendering iterations to start from: it is a starting point,
    # not a result (the refined pose must pass every check); 12, the structure baseline's success threshold
    coarse_min_inliers: int = 12
    # stop iterating once rendering from the new estimate would change fewer than this share of the landmarks
    # to match: those that enter or leave the visible set, and those seen along a ray more than
    # rerender_angle_deg from the one their descriptor was rendered along. The next iteration would match
    # nearly the same descriptors and find nearly the same pose. 0: run every iteration
    stop_change: float = 0.05
    # within one query, a landmark keeps the descriptor it got while the camera sees it along a ray at most this
    # far from the one it was rendered for (favormap.localize.descriptors.SeenRays; 0: rendered every time)
    rerender_angle_deg: float = 1.0
    # "rendered" (FaVoR: rendered from the voxel grids), "mean" (each landmark's mean observed descriptor) or
    # "nearest" (observed in the mapping frame nearest in direction; favormap.localize.descriptors)
    descriptors: str = "rendered"
    view_limits: ViewLimits = field(default_factory=_localizer_view_limits)  # which landmarks are tried
    device: str = "cpu"  # where voxels render: "cpu" (NumPy; torch is not imported) or a torch device
    seed: int = 0  # RANSAC's
    # CPU threads for torch/OpenCV: None leaves the process's pools alone; "auto" sizes them by favormap.threads'
    # rule (and follows the machine's load), a number fixes them. Either way the BLAS libraries then run each
    # product on its calling thread while a query is localized (favormap.threads.serial_blas): the localizer
    # runs its stages on threads of its own (extraction beside the first rendering, rendering beside matching);
    # and large temporaries come from reused heap blocks (favormap.heap.reuse_freed_blocks, process-wide)
    threads: int | str | None = None

    def ransac_threshold(self, epipolar_limit_px: float | None) -> float:
        """The PnP-RANSAC threshold (px) for a map whose build measured ``epipolar_limit_px`` (None: not
        recorded): ``ransac_max_error_px`` where given. A correct correspondence's reprojection error in the
        query carries the errors of the mapping poses its landmark was triangulated from; where those poses
        fit their images to a few pixels only (motion capture, KinectFusion), a threshold below that
        refuses correct correspondences and RANSAC settles on a few lucky ones."""
        if self.ransac_max_error_px is not None:
            return float(self.ransac_max_error_px)
        return max(self.min_ransac_px, self.pose_noise_ransac * (epipolar_limit_px or 0.0))

    def __post_init__(self):
        v = self.landmark_sigma_px
        if not (v in ("landmark", "map") or (isinstance(v, (int, float)) and 0 <= v < float("inf"))):
            raise InputError(f"landmark_sigma_px must be 'landmark', 'map' or a number of pixels >= 0, not {v!r}")
        r = self.ransac_max_error_px
        if not (r is None or (isinstance(r, (int, float)) and 0 < r < float("inf"))):
            raise InputError(f"ransac_max_error_px must be a number of pixels > 0 (or None: the map's), not {r!r}")
        f = self.fit_max_error_px
        if not (f is None or (isinstance(f, (int, float)) and 0 < f < float("inf"))):
            raise InputError(f"fit_max_error_px must be a number of pixels > 0 (or None: off), not {f!r}")
        if not (0 < self.min_ransac_px < float("inf") and 0 <= self.pose_noise_ransac < float("inf")):
            raise InputError("min_ransac_px must be > 0 and pose_noise_ransac >= 0")
        if not (0 <= self.guided_radius_px < float("inf") and 0 <= self.guided_gate_sigma < float("inf")):
            raise InputError("guided_radius_px and guided_gate_sigma must be numbers >= 0")
        if self.guided_below_inliers is not None and self.guided_below_inliers < 0:
            raise InputError("guided_below_inliers must be >= 0 (or None: every pose)")
        if not (isinstance(self.stop_change, (int, float)) and 0 <= self.stop_change <= 1):
            raise InputError(f"stop_change must be a share in [0, 1], not {self.stop_change!r}")
        if not (isinstance(self.rerender_angle_deg, (int, float)) and 0 <= self.rerender_angle_deg <= 180):
            raise InputError(
                f"rerender_angle_deg must be a number of degrees in [0, 180], not {self.rerender_angle_deg!r}"
            )
        if self.refine_noise not in ("fixed", "estimated"):
            raise InputError(f"refine_noise must be 'fixed' or 'estimated', not {self.refine_noise!r}")
        if not (isinstance(self.keypoint_sigma_px, (int, float)) and 0 < self.keypoint_sigma_px < float("inf")):
            raise InputError(f"keypoint_sigma_px must be a number of pixels > 0, not {self.keypoint_sigma_px!r}")
        if not (self.threads in (None, "auto") or (isinstance(self.threads, int) and self.threads >= 1)):
            raise InputError(f"threads must be None, 'auto' or an integer >= 1, not {self.threads!r}")
