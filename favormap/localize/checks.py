"""The localizer's success checks: whether a pose is reported as a success (``SuccessChecks``), the
confirmation of weak poses by the prior-free estimate, and the assembled result.

:class:`SuccessChecking` is a part of :class:`favormap.localize.Localizer`: it uses the localizer's
``config``, ``map``, ``positions``, ``scale`` and its ``_global_pose`` step."""

from __future__ import annotations

import numpy as np

from ..geometry import from_rigid3d, pose_error
from ..visibility import visible_mask
from .result import IterationResult, LocalizationResult, Query


class SuccessChecking:
    def _confirm(self, q: Query, res: LocalizationResult, start: np.ndarray, t: dict) -> None:
        """A successful ``res`` with fewer than ``SuccessChecks.confirm_below_inliers`` inliers is
        refused (in place; its pose becomes ``start``, where its iterations began) unless the
        prior-free matches confirm it: ``confirm_min_inliers`` of them lie within the RANSAC threshold of
        the pose (:meth:`_prior_free_support`), or the prior-free estimate agrees with it. For a pose
        refined from that estimate this asks that the rendering iterations did not carry it away:
        with a looser ratio test (0.9) the fox's wallpaper query 0072 got a correct coarse pose (0.01
        units off) that the iterations moved 6.8 units, to the wallpaper's false consensus.

        The inliers counted are those of the last rendering iteration (matched by descriptor): the
        guided step's (matched by projection) grow with any pose that lines a repeated pattern up,
        and at a 3 px radius lifted both wallpaper queries above 100 inliers (two false successes)."""
        c = self.config.checks
        render = [it.num_inliers for it in res.iterations if it.kind == "render"]
        evidence = render[-1] if render else res.num_inliers
        if not res.success or evidence >= c.confirm_below_inliers:
            return
        coarse, it = self._global_pose(q, t)
        if coarse is None and c.confirm_min_inliers and it.num_inliers >= c.confirm_min_inliers:
            coarse = it.cam_from_world  # too few inliers to localize from, enough to agree with
        support = self._prior_free_support(q, res.cam_from_world)
        res.checks["prior_free_support"] = support
        if coarse is not None:
            change = self._change(coarse, res.cam_from_world)
            res.checks["confirmation_change"], res.checks["confirmation_change_deg"] = change
        else:
            res.checks["confirmation_change"] = None
        if coarse is not None and not self._apart(change):
            return
        if c.confirm_min_inliers and support >= c.confirm_min_inliers:
            return  # the matches found without the prior agree with the pose, whatever RANSAC chose among them
        if coarse is not None:
            why = (
                f"it lies {change[0]:.3f} x landmark depth, {change[1]:.2f} deg from the estimate without the prior, "
                f"and explains {support} of its matches"
            )
        else:
            why = f"without the prior no pose was found ({it.num_matches} matches, {it.num_inliers} inliers)"
        res.success, res.cam_from_world, res.covariance = False, start, None
        res.message = (
            f"the pose has only {evidence} inliers matched by descriptor (fewer than {c.confirm_below_inliers}) "
            f"and is not confirmed by matching against all landmarks: {why}"
        )

    def _prior_free_support(self, q: Query, pose: np.ndarray) -> int:
        """How many of the prior-free step's matches (every landmark's mean descriptor against the query,
        Lowe's test) ``pose`` explains: in front and within the RANSAC threshold of their keypoint. Found
        without any prior, they confirm a pose they agree with even where RANSAC's estimate from them alone
        settled elsewhere: of ~300 such matches a wrong pose explains a few by chance (0.08 % of the image
        lies within 9 px of a point)."""
        if q.global_matches is None or len(q.global_matches[1]) == 0:
            return 0
        X, kp_idx = q.global_matches
        within = self._within(q.cam.K, pose, X, q.feats.keypoints[kp_idx], self.config.ransac_max_error_px)
        return int(np.sum(within))

    def _change(self, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
        """How far apart two poses are: (translation / median landmark depth, rotation in deg)."""
        dt, dr = pose_error(a, b)
        return dt / self.scale, dr

    def _apart(self, change: tuple[float, float]) -> bool:
        """Whether a :meth:`_change` exceeds ``checks.max_iteration_change``."""
        limit = self.config.checks.max_iteration_change
        return change[0] > limit[0] or change[1] > limit[1]

    def _leaves(self, ans: dict, anchor: np.ndarray) -> bool:
        """Whether a PnP solution ``ans`` with few inliers lies beyond ``checks.max_iteration_change``
        of ``anchor`` (so that :meth:`_confirm` would refuse it)."""
        if int(ans["num_inliers"]) >= self.config.checks.confirm_below_inliers:
            return False
        return self._apart(self._change(from_rigid3d(ans["cam_from_world"]), anchor))

    def _result(
        self, q: Query, last: dict | None, iters: list[IterationResult], t: dict, start: np.ndarray, message: str = ""
    ) -> LocalizationResult:
        """Apply the success checks to the last iteration and assemble the result."""
        ok_iters = [it for it in iters if it.success]
        final = iters[-1]
        checks: dict = {}
        reason = message
        if not message:
            if not final.success:
                reason = (
                    f"too few inliers ({final.num_matches} matches, {final.num_inliers} inliers, {final.num_visible} "
                    f"visible landmarks; need {self.config.checks.min_inliers} inliers)"
                )
                if final.num_visible < self.config.checks.min_inliers:
                    reason += (
                        "; the prior sees almost none of the map's landmarks: is it world_from_cam in OpenCV "
                        "axes (x right, y down, z forward), in the map's frame?"
                    )
            else:
                checks, reason = self._checks(q, last, iters)
        success = not reason
        est = ok_iters[-1].cam_from_world if ok_iters else None
        aligned = q.aligned if last is not None and q.aligned is not None else None
        return LocalizationResult(
            success=success,
            cam_from_world=est if success else start,
            num_matches=final.num_matches,
            num_inliers=final.num_inliers,
            iterations=iters,
            timings=t,
            message=reason,
            checks=checks,
            keypoints=q.feats.keypoints,
            matches=None if last is None else last["matches"],
            inlier_mask=None if last is None else last["inliers"],
            match_similarity=None if last is None else last["similarity"],
            estimate=est,
            by_projection=None if last is None or "by_descriptor" not in last else ~last["by_descriptor"],
            camera=q.cam,
            aligned=aligned if aligned is not None and len(aligned) == len(last["matches"]) else None,
        )

    def _checks(self, q: Query, last: dict, iters: list[IterationResult]) -> tuple[dict, str]:
        """Measured values of the success checks and the first one that fails ('' when all pass)."""
        c = self.config.checks
        final = iters[-1]
        pose = final.cam_from_world
        vals: dict = {"inliers": final.num_inliers, "inlier_ratio": final.num_inliers / max(final.num_matches, 1)}
        g = max([i for i, it in enumerate(iters) if it.kind == "global"], default=-1)
        render_iters = iters[g + 1 :]  # the refinement (render, guided) that gave this pose
        if len(render_iters) >= 2:
            change = self._change(render_iters[-1].cam_from_world, render_iters[-2].cam_from_world)
            vals["iteration_change"], vals["iteration_change_deg"] = change
        rows = last["matches"][last["inliers"], 0]
        vis = (
            visible_mask(
                self.positions[rows],
                q.cam,
                pose,
                self.map.view_dir[rows],
                self.map.view_angle[rows],
                self.map.depth_range[rows],
                self.config.view_limits,
            )
            if len(rows)
            else np.zeros(0, bool)
        )
        vals["visible_inliers"] = float(vis.mean()) if len(vis) else 0.0
        if vals["inlier_ratio"] < c.min_inlier_ratio:
            return (
                vals,
                f"low inlier ratio ({final.num_inliers} of {final.num_matches} matches; need {c.min_inlier_ratio:.0%})",
            )
        if len(render_iters) >= 2 and self._apart(change):
            return vals, (
                f"iterations disagree (last two estimates {vals['iteration_change']:.3f} x landmark depth, "
                f"{vals['iteration_change_deg']:.2f} deg apart)"
            )
        if vals["visible_inliers"] < c.min_visible_inliers:
            return vals, (
                f"only {vals['visible_inliers']:.0%} of the inlier landmarks are visible from the estimated pose "
                f"(need {c.min_visible_inliers:.0%})"
            )
        return vals, ""
