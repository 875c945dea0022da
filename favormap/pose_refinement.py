"""pose refinement: the mapping poses adjusted to the images by bundle adjustment (pycolmap).

Given poses that fit their images less well than the extractor places keypoints (motion capture with a
time offset and a rolling shutter, KinectFusion's drift) give every landmark the error of the few poses
it was triangulated from. Landmarks of different frames then disagree with each other by pixels, and a
query matched to them can be located no better than that disagreement. Here the poses and the
triangulated landmarks are refined together on the tracks' reprojection errors (COLMAP's bundle
adjuster, Cauchy loss at the extractor's keypoint precision, intrinsics fixed), each camera centre held
near its given position by a Gaussian prior: the map keeps the world frame and the units of the poses it
was given, and only the part of the poses that the images contradict moves.

The prior's standard deviation is the camera-centre error the measured pose noise implies: the right
tracking matches' median distance from their epipolar lines (px), times the landmarks' median depth,
over the focal length.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

from .geometry import (
    camera_centers,
    from_rigid3d,
    move_poses,
    nearest_rotation,
    project,
    rotation_angle_deg,
    rotvec_to_rotmat,
    to_rigid3d,
    transform_points,
    umeyama,
)
from .io import Camera
from .least_squares import rotation_jacobian, schur_step
from .triangulation import Landmarks


@dataclass
class PoseRefinement:
    """Stage boundary: the refined mapping poses and how far they moved from the given ones."""

    cam_from_world: np.ndarray  # (M, 4, 4) refined
    center_shift: np.ndarray  # (M,) distance each camera centre moved (world units)
    rotation_change_deg: np.ndarray  # (M,) angle each camera turned
    camera_offset: np.ndarray  # (3, 3) the rotation the given poses share on the camera side (given ~ offset @ refined)
    prior_sigma: float  # standard deviation of the camera-centre prior (world units)
    initial_rms_px: float  # reprojection error of the observations before and after (RMS over the residuals)
    final_rms_px: float

    @property
    def cam_from_rig(self) -> np.ndarray:
        """The camera's pose in the frame of the given poses: the rotation they share on the camera side."""
        T = np.eye(4)
        T[:3, :3] = self.camera_offset.T
        return T

    def stats(self) -> dict:
        """The build summary's figures of the refinement."""
        return {
            "poses_refined": True,
            "pose_prior_sigma": float(self.prior_sigma),
            "pose_center_shift_median": float(np.median(self.center_shift)),
            "pose_rotation_change_median_deg": float(np.median(self.rotation_change_deg)),
            "pose_camera_offset_deg": float(rotation_angle_deg(self.camera_offset)),
            "pose_refinement_rms_px": [round(self.initial_rms_px, 3), round(self.final_rms_px, 3)],
        }


def poses_need_refinement(epipolar_median_px: float, keypoint_precision_px: float) -> bool:
    """Whether the given poses fit their images less well than the extractor places keypoints: the right
    tracking matches lie farther from their epipolar lines (median, px) than ``keypoint_precision_px``.
    False when the median was not measured (NaN: an epipolar limit given by the user)."""
    return bool(np.isfinite(epipolar_median_px) and epipolar_median_px > keypoint_precision_px)


def median_depth(lms: Landmarks, cam_from_world: np.ndarray) -> float:
    """The median depth of the landmarks' observations in their frames (world units)."""
    f = np.asarray(lms.tracks.frame_idx)
    T = np.asarray(cam_from_world)[f]
    X = lms.positions[lms.tracks.track_of_obs]
    depth = np.einsum("nj,nj->n", T[:, 2, :3], X) + T[:, 2, 3]
    return float(np.median(depth[depth > 0])) if (depth > 0).any() else 0.0


def refine_poses(
    lms: Landmarks,
    cam_from_world: np.ndarray,
    cameras: list[Camera],
    pixel_noise: float,
    loss_px: float = 1.0,
    iterations: int = 100,
) -> PoseRefinement:
    """Bundle adjustment of the poses ``cam_from_world`` (M, 4, 4) of the working pinhole ``cameras``
    (one per frame) and the landmarks ``lms`` on their observations, each camera centre held to its
    given position by a Gaussian prior of the error ``pixel_noise`` px of pose noise implies (that
    many pixels at the landmarks' median depth, over the median focal length); then the refined poses
    are put back into the frame of the given ones (:func:`frame_alignment`). Cauchy loss of scale
    ``loss_px``; intrinsics fixed. Returns the refined poses (the landmarks are to be triangulated again
    from them)."""
    import pycolmap

    T0 = np.asarray(cam_from_world, np.float64)
    depth = median_depth(lms, T0)
    sigma = pixel_noise * depth / float(np.median([np.mean(c.focal) for c in cameras]))
    problem = _adjustment_problem(lms, T0, cameras)
    centers = camera_centers(T0)
    priors = _center_priors(problem.rec, centers, sigma)
    with quiet_colmap():
        adjuster = pycolmap.create_pose_prior_bundle_adjuster(
            _adjuster_options(loss_px, iterations, len(lms)),
            pycolmap.PosePriorBundleAdjustmentOptions(),
            problem.config,
            priors,
            problem.rec,
        )
        adjuster.solve()
    rec = problem.rec
    T = np.stack([from_rigid3d(rec.image(f + 1).cam_from_world()) for f in range(len(T0))])
    S, offset = frame_alignment(T, T0, depth)
    T = move_poses(T, S)
    X = transform_points(S, np.stack([rec.point3D(i).xyz for i in problem.point_ids]))
    angle = rotation_angle_deg(np.einsum("nij,nkj->nik", T[:, :3, :3], T0[:, :3, :3]))
    return PoseRefinement(
        cam_from_world=T,
        center_shift=np.linalg.norm(camera_centers(T) - centers, axis=1),
        rotation_change_deg=angle,
        camera_offset=offset,
        prior_sigma=float(sigma),
        initial_rms_px=_rms(lms, T0, cameras),
        final_rms_px=_rms(lms, T, cameras, X),
    )


@dataclass
class _Adjustment:
    """The bundle adjustment's problem in pycolmap's terms: frame f is image f + 1."""

    rec: object  # pycolmap.Reconstruction: the cameras, the images with their observations, the landmarks
    config: object  # pycolmap.BundleAdjustmentConfig: every image and landmark variable, the intrinsics fixed
    point_ids: list[int]  # each landmark's point id


def _adjustment_problem(lms: Landmarks, T0: np.ndarray, cameras: list[Camera]) -> _Adjustment:
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids, image_cam = _add_cameras(rec, cameras)
    point2d = _add_images(rec, lms, T0, image_cam)
    config = pycolmap.BundleAdjustmentConfig()
    for f in range(len(T0)):
        config.add_image(f + 1)
    for c in cam_ids:
        config.set_constant_cam_intrinsics(c)
    frame = np.asarray(lms.tracks.frame_idx, np.int64)
    offsets = lms.tracks.offsets
    point_ids = []
    for j in range(len(lms)):  # pycolmap takes a track element by element (~0.1 s for 15,000 landmarks)
        tr = pycolmap.Track()
        for o in range(offsets[j], offsets[j + 1]):
            tr.add_element(int(frame[o]) + 1, int(point2d[o]))
        point_ids.append(rec.add_point3D(np.asarray(lms.positions[j], np.float64), tr))
        config.add_variable_point(point_ids[-1])
    return _Adjustment(rec, config, point_ids)


def _add_cameras(rec, cameras: list[Camera]) -> tuple[list[int], list[int]]:
    """One pycolmap camera per distinct camera of the frames; returns their ids and each frame's."""
    cam_ids: dict[tuple, int] = {}
    image_cam = []
    for c in cameras:
        key = (c.model, c.width, c.height, tuple(np.round(np.asarray(c.params, np.float64), 9)))
        if key not in cam_ids:
            pc = c.to_pycolmap()
            pc.camera_id = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(pc)
            cam_ids[key] = pc.camera_id
        image_cam.append(cam_ids[key])
    return list(cam_ids.values()), image_cam


def _add_images(rec, lms: Landmarks, T0: np.ndarray, image_cam: list[int]) -> np.ndarray:
    """One image per frame at its given pose, its keypoints the landmarks' observations in it; returns
    each observation's index among its frame's keypoints."""
    import pycolmap

    frame = np.asarray(lms.tracks.frame_idx, np.int64)
    xy = np.asarray(lms.tracks.xy, np.float64)
    order = np.argsort(frame, kind="stable")  # each frame's observations, in one run
    starts = np.searchsorted(frame[order], np.arange(len(T0) + 1))
    point2d = np.empty(len(frame), np.int64)
    for f in range(len(T0)):
        rows = order[starts[f] : starts[f + 1]]
        point2d[rows] = np.arange(len(rows))
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{f:06d}", keypoints=xy[rows], camera_id=image_cam[f], image_id=f + 1),
            to_rigid3d(T0[f]),
        )
    return point2d


def _center_priors(rec, centers: np.ndarray, sigma: float) -> list:
    """Each image's camera centre held near ``centers`` by a Gaussian prior of standard deviation ``sigma``."""
    import pycolmap

    priors = []
    for f in range(len(centers)):
        prior = pycolmap.PosePrior(
            position=centers[f],
            position_covariance=np.eye(3) * max(sigma, 1e-12) ** 2,
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
        )
        prior.corr_data_id = rec.image(f + 1).data_id
        priors.append(prior)
    return priors


def _adjuster_options(loss_px: float, iterations: int, n_landmarks: int):
    """COLMAP's bundle-adjustment options: intrinsics fixed, Cauchy loss of scale ``loss_px``."""
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = float(loss_px)
    options.ceres.solver_options.max_num_iterations = int(iterations)
    options.ceres.solver_options.num_threads = 1 if n_landmarks < 1000 else -1
    return options


def frame_alignment(
    refined: np.ndarray, given: np.ndarray, lever: float, rounds: int = 5
) -> tuple[np.ndarray, np.ndarray]:
    """(S, offset): the similarity S (4x4, x_given = s R x_refined + t) that puts the refined poses back
    into the frame of the given ones, fitted to all the given poses say of the frame: their camera centres and their
    orientations. The centre priors of the bundle adjustment leave the frame free where the centres do not
    fix it (a rotation about the line of a straight path) and turn it by their own noise where the path is
    short; the orientations fix both. Each camera contributes its centre and three points ``lever`` along
    its axes (Umeyama): with the lever the ratio of a centre's error to an orientation's (both from one pixel
    noise: the landmarks' median depth), both weigh by their noise.

    The given orientations may share one rotation on the camera side that the images contradict (the
    hand-eye calibration of a motion-capture rig): it is estimated with the similarity, alternately, and
    left out of the orientations the frame is fitted to, so that it does not turn the world."""
    c_ref, c_given = camera_centers(refined), camera_centers(given)
    offset = np.eye(3)  # given ~ offset @ true, on the camera side
    S = np.eye(4)
    for _ in range(rounds):
        R_given = np.einsum("ji,njk->nik", offset, given[:, :3, :3])
        src = np.concatenate([c_ref[:, None, :], c_ref[:, None, :] + lever * refined[:, :3, :3]], 1)
        dst = np.concatenate([c_given[:, None, :], c_given[:, None, :] + lever * R_given], 1)
        S = umeyama(src.reshape(-1, 3), dst.reshape(-1, 3))
        R_moved = move_poses(refined, S)[:, :3, :3]
        offset = nearest_rotation(np.einsum("nij,nkj->ik", given[:, :3, :3], R_moved))
    return S, offset


def _rms(lms: Landmarks, cam_from_world: np.ndarray, cameras: list[Camera], positions=None) -> float:
    """RMS reprojection error (px) of the observations of ``lms`` (at ``positions``, or their own)."""
    X = (lms.positions if positions is None else positions)[lms.tracks.track_of_obs]
    f = np.asarray(lms.tracks.frame_idx)
    uv = project(np.stack([c.K for c in cameras])[f], np.asarray(cam_from_world)[f], X)
    return float(np.sqrt(np.mean(np.sum((uv - lms.tracks.xy) ** 2, axis=1))))


@contextlib.contextmanager
def quiet_colmap(level: str = "ERROR"):
    """COLMAP's glog output at ``level`` (ERROR, FATAL) only, for the duration of the block."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(getattr(pycolmap.logging.Level, level))
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


@dataclass
class CameraRotation:
    """Stage boundary: the rotation between the given poses and the camera the images see.

    Poses from motion capture or from a depth camera's tracker describe a body the camera rides on; a
    hand-eye calibration that is off by a fraction of a degree turns every camera the same way, and every
    landmark is triangulated with that error, in a direction that changes with the view. Here that
    rotation is estimated from the tracks with the given poses held fixed."""

    cam_from_rig: np.ndarray  # (4, 4) the camera's pose in the frame of the given poses (rotation only)
    initial_rms_px: float  # the tracks' reprojection error (RMS over the residuals), before and after
    final_rms_px: float
    # the angle between the estimates from the first and from the second half of the frames: a calibration's
    # error is the same all along a recording, pose noise that a shared rotation happens to fit is not
    halves_apart_deg: float

    @property
    def angle_deg(self) -> float:
        return float(rotation_angle_deg(self.cam_from_rig[:3, :3]))

    @property
    def holds(self) -> bool:
        """Whether the two halves of the recording agree on the rotation: their estimates lie closer to each
        other than HALVES_AGREEMENT times its angle. On the TUM desk recording 0.98 deg with halves 0.23 deg
        apart; on a 7-Scenes kitchen's KinectFusion poses 0.33 deg with halves 1.0 deg apart (drift, not a
        calibration)."""
        return self.halves_apart_deg <= HALVES_AGREEMENT * self.angle_deg

    def camera_poses(self, rig_from_world: np.ndarray) -> np.ndarray:
        """(M, 4, 4) the cameras' poses ``cam_from_world`` of the given poses ``rig_from_world``."""
        return np.einsum("ij,njk->nik", self.cam_from_rig, rig_from_world)

    def stats(self) -> dict:
        """The build summary's figures of the estimate."""
        return {
            "camera_rotation_deg": round(self.angle_deg, 4),
            "camera_rotation_halves_apart_deg": round(self.halves_apart_deg, 4),
            "camera_rotation_applied": self.holds,
            "camera_rotation_rms_px": [round(self.initial_rms_px, 3), round(self.final_rms_px, 3)],
        }


# CameraRotation.holds: the halves' estimates at most this share of the angle apart. A calibration's turn on the
# TUM desk recording: its halves 0.2-0.5 of its angle apart as the tracks vary (maps of other frame pairings);
# a 7-Scenes kitchen's drift: 1.8-4.6 times; the bound lies between them with a factor of two to either side
HALVES_AGREEMENT = 1.0


def estimate_camera_rotation(
    lms: Landmarks,
    rig_from_world: np.ndarray,
    cameras: list[Camera],
    loss_px: float = 1.0,
    iterations: int = 30,
    order: np.ndarray | None = None,
) -> CameraRotation:
    """The one rotation ``cam_from_rig`` shared by every frame that, with the landmarks, best explains the
    observations of ``lms`` when the given poses ``rig_from_world`` (M, 4, 4) stay fixed, from all frames and
    from each half of them (CameraRotation.holds); see :func:`_solve_camera_rotation`. ``order``: the frames
    in the order the recording went (None: as given; the build passes the order tracking walked, Tracks.frame_order),
    whose first and second half are the halves."""
    T = np.asarray(rig_from_world, np.float64)
    Q, rms0, rms1 = _solve_camera_rotation(lms, T, cameras, loss_px, iterations)
    walk = np.arange(len(T)) if order is None else np.asarray(order, np.int64)
    halves = [
        _solve_camera_rotation(_in_frames(lms, part), T, cameras, loss_px, iterations)[0]
        for part in np.array_split(walk, 2)
    ]
    cam_from_rig = np.eye(4)
    cam_from_rig[:3, :3] = Q
    return CameraRotation(cam_from_rig, rms0, rms1, float(rotation_angle_deg(halves[0].T @ halves[1])))


def _in_frames(lms: Landmarks, frames: np.ndarray) -> Landmarks:
    """The landmarks of ``lms`` with their observations in ``frames``, those of at least two of them."""
    keep = np.isin(lms.tracks.frame_idx, frames)
    n = np.bincount(lms.tracks.track_of_obs[keep], minlength=len(lms))
    keep &= n[lms.tracks.track_of_obs] >= 2
    rows = np.flatnonzero(n >= 2)
    return Landmarks(lms.positions[rows], lms.tracks.select(keep), lms.reproj_errors[keep], lms.angles_deg[rows])


def _solve_camera_rotation(
    lms: Landmarks, T: np.ndarray, cameras: list[Camera], loss_px: float, iterations: int
) -> tuple[np.ndarray, float, float]:
    """(Q, RMS before, RMS after): the rotation Q with cam_from_world = Q @ T[frame] and the landmarks'
    positions minimising the Cauchy cost (scale ``loss_px``) of the reprojection errors of ``lms``:
    Levenberg-Marquardt on the joint problem, each step solved through the Schur complement of the
    landmarks' 3x3 blocks (the three rotation parameters left)."""
    tid = np.asarray(lms.tracks.track_of_obs, np.int64)
    f = np.asarray(lms.tracks.frame_idx, np.int64)
    xy = np.asarray(lms.tracks.xy, np.float64)
    K = np.stack([c.K for c in cameras])[f]
    R, t = T[f, :3, :3], T[f, :3, 3]
    n = len(lms)
    X = np.asarray(lms.positions, np.float64).copy()
    Q = np.eye(3)

    def residuals(Q, X):
        c = np.einsum("ij,nj->ni", Q, np.einsum("nij,nj->ni", R, X[tid]) + t)
        z = c[:, 2:3]
        uv = np.stack([K[:, 0, 0], K[:, 1, 1]], 1) * c[:, :2] / z + K[:, :2, 2]
        return uv - xy, c

    def cost(r):
        return float(np.sum(loss_px**2 * np.log1p(np.sum(r**2, 1) / loss_px**2)))

    r, c = residuals(Q, X)
    rms0, best, lam = float(np.sqrt(np.mean(np.sum(r**2, 1)))), cost(r), 1e-3
    for _ in range(iterations):
        w = 1.0 / (1.0 + np.sum(r**2, 1) / loss_px**2)  # Cauchy's IRLS weights
        x, y, z = c[:, 0], c[:, 1], c[:, 2]
        fx, fy = K[:, 0, 0], K[:, 1, 1]
        P = np.zeros((len(c), 2, 3))  # d pixel / d camera-frame point
        P[:, 0, 0], P[:, 0, 2] = fx / z, -fx * x / z**2
        P[:, 1, 1], P[:, 1, 2] = fy / z, -fy * y / z**2
        J_w = P @ rotation_jacobian(c)  # d residual / d rotation update (Q <- exp([w]x) Q)
        J_X = P @ (Q @ R)  # d residual / d landmark position
        for _ in range(10):  # damped until the cost falls
            dw, dX = schur_step(J_w, J_X, r, w, tid, n, lam, point_ridge=1e-9, shared_ridge=0.0)
            Qn, Xn = rotvec_to_rotmat(dw) @ Q, X + dX
            rn, cn = residuals(Qn, Xn)
            if np.all(cn[:, 2] > 0) and cost(rn) < best:
                Q, X, r, c, best, lam = Qn, Xn, rn, cn, cost(rn), max(lam / 10, 1e-9)
                break
            lam *= 10
        else:
            break
        if np.linalg.norm(dw) < 1e-8:
            break
    return Q, rms0, float(np.sqrt(np.mean(np.sum(r**2, 1))))
