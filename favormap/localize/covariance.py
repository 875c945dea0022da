"""The uncertainty of a localized pose (:class:`PoseCovariance`), as the weighted refinement
(favormap.localize.refine) reports it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PoseCovariance:
    """Uncertainty of a ``cam_from_world`` estimate: ``rotation`` (3, 3) rad^2 of the small rotation
    applied on the camera side (T -> exp(w) T), ``center`` (3, 3) map units^2 of the camera centre in
    world axes, ``cross`` (3, 3) their covariance (rotation rows, centre columns). With a noise model
    fitted to the query (:func:`estimate_noise`), also its factors: how many times the map's landmark
    covariances the landmarks' errors were (variance), and the keypoint noise (px)."""

    rotation: np.ndarray
    center: np.ndarray
    cross: np.ndarray
    landmark_scale: float | None = None
    keypoint_sigma_px: float | None = None

    @classmethod
    def from_left_perturbation(cls, cam_from_world: np.ndarray, cov6: np.ndarray) -> PoseCovariance:
        """From the covariance of (w, v) with T -> [exp(w) R | exp(w) t + v]: the centre
        c = -R^T t moves by -R^T v to first order (w cancels)."""
        R = cam_from_world[:3, :3]
        A = -R.T
        return cls(cov6[:3, :3].copy(), A @ cov6[3:, 3:] @ A.T, cov6[:3, 3:] @ A.T)

    def turned(self, A: np.ndarray) -> PoseCovariance:
        """The covariance of ``[A | 0] @ cam_from_world`` (the same camera centre, its axes turned by the
        rotation ``A``): exp(w) T becomes exp(A w) [A | 0] T."""
        return PoseCovariance(
            A @ self.rotation @ A.T, self.center.copy(), A @ self.cross, self.landmark_scale, self.keypoint_sigma_px
        )

    @property
    def center_std(self) -> np.ndarray:
        """1-sigma of the camera centre along the world axes (map units)."""
        return np.sqrt(np.clip(np.diag(self.center), 0, None))

    @property
    def rotation_std_deg(self) -> float:
        """1-sigma of the rotation about its least certain axis (degrees)."""
        return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(self.rotation).max(), 0.0))))

    def to_json(self) -> dict:
        return {
            "center_std": self.center_std.tolist(),
            "rotation_std_deg": self.rotation_std_deg,
            "center_covariance": self.center.tolist(),
            "rotation_covariance": self.rotation.tolist(),
            **(
                {}
                if self.landmark_scale is None
                else {
                    "noise_model": {"landmark_scale": self.landmark_scale, "keypoint_sigma_px": self.keypoint_sigma_px}
                }
            ),
        }
