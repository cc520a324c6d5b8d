"""Validated configuration of the back end: the loop-closure pool, CLIPPER, the pose graph, the
fix gate and the sanity gate."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from meridian_torch.config.base import StrictModel
from meridian_torch.config.matching import ClipperConfig

__all__ = ["BackendConfig"]


class BackendConfig(StrictModel):
    """Robust pose graph and incremental localizer.

    Loop-closure consistency noise grows linearly with the odometry path length l between two
    submaps: sigma_yaw(l) = sigma_yaw_deg + sigma_yaw_deg_per_m * l, sigma_t(l) likewise; the
    gates epsilon equal the sigmas (reference).
    """

    sigma_yaw_deg: float = Field(default=5.0, gt=0, description="[paper] yaw noise of a candidate pair at l = 0")
    sigma_yaw_deg_per_m: float = Field(default=0.02, ge=0, description="[paper] growth of the yaw noise per metre")
    sigma_t_m: float = Field(default=2.0, gt=0, description="[paper] translation noise at l = 0")
    sigma_t_m_per_m: float = Field(default=0.05, ge=0, description="[paper] growth of the translation noise per metre")
    path_length_scaling: bool = Field(
        default=True, description="False = constant noise (the paper's 'without path-length scaling' ablation)"
    )
    min_associations: int = Field(default=3, ge=1, description="hypotheses with fewer associations are no candidates")
    fuse_quality: bool = Field(
        default=True, description="affinity = cbrt(s * q_i * q_j) with q = probability / best of `quality_scope`"
    )
    quality_scope: Literal["submap", "patch"] = Field(
        default="submap",
        description="a candidate's quality is its probability relative to the best hypothesis of its submap "
        "over every patch it was matched against (verified probabilities compare across patches), or of its "
        "(submap, patch) pair (the reference's frequency ratio)",
    )
    affinity_eps: float = Field(default=1e-4, ge=0, description="affinities at or below this are dropped")
    max_clipper_candidates: int = Field(
        default=4000,
        ge=2,
        description="CLIPPER problems (candidates left after pruning those that cannot join the densest "
        "clique) larger than this are solved in even chunks, then once more on the pooled chunk inliers "
        "(reference 100000 before pruning; a dense float64 4000^2 matrix is 128 MB); the final pass cuts a "
        "larger candidate set into windows of consecutive submaps before building any graph (its graph is "
        "nearly complete), so its memory does not grow with the drive",
    )
    clipper: ClipperConfig = Field(
        default_factory=lambda: ClipperConfig(rounding="support"),
        description="CLIPPER on the loop-closure graph; 'support' rounding keeps every mutually consistent "
        "candidate of the converged solution (the reference's round(F) drops members of weighted cliques)",
    )
    odom_trans_sigma_m: float = Field(default=0.05, gt=0, description="odometry between-factor sigma per frame step (reference)")
    odom_rot_sigma_deg: float = Field(default=0.05, gt=0, description="odometry between-factor yaw sigma per frame step (reference)")
    odom_trans_sigma_m_per_sqrt_m: float = Field(
        default=0.05,
        ge=0,
        description="its square times a step's length (m) is added to the step's x, y variance (a random walk "
        "in distance: the odometry's weight then depends less on the frame rate; 0 = per step only, the reference)",
    )
    odom_rot_sigma_deg_per_sqrt_m: float = Field(
        default=0.05, ge=0, description="its square times a step's length (m) is added to the step's yaw variance"
    )
    prior_trans_sigma_m: float = Field(default=2.0, gt=0, description="loop-closure prior sigma x, y (reference)")
    prior_rot_sigma_deg: float = Field(default=5.0, gt=0, description="loop-closure prior yaw sigma (reference)")
    prior_sigma_probability: float | None = Field(
        default=0.15,
        gt=0,
        le=1,
        description="a loop closure whose hypothesis probability p (with verification, the default: the share of "
        "the submap aligned beyond chance) is below this gets its pose-graph prior sigmas scaled by sqrt(this / p), "
        "at most prior_sigma_max_scale (the online gate keeps the nominal sigmas): the closures turned by several "
        "degrees are mostly the less probable ones; null: every closure the same sigmas",
    )
    prior_sigma_max_scale: float = Field(
        default=3.0, ge=1, description="the largest scale of a loop closure's prior sigmas (prior_sigma_probability)"
    )
    attempt_min_inliers: int = Field(
        default=3,
        ge=1,
        description="gate 1: pre-fix inlier loop closures needed before a fix attempt (a re-match of all "
        "submaps; reference 1): fewer let chance-consistent candidates seed wrong fixes",
    )
    fix_min_inliers: int = Field(
        default=6, ge=1, description="[paper] global fix: >= 6 inlier loop closures; also how many submaps after "
        "the fix are awaited before they judge it"
    )
    fix_min_inlier_fraction: float = Field(
        default=0.5, gt=0, le=1, description="[paper] ... and inliers >= this fraction of the submaps so far"
    )
    fix_min_mean_probability: float | None = Field(
        default=0.15,
        gt=0,
        le=1,
        description="... and the inliers' mean hypothesis probability >= this (null: no such test). Measured on "
        "the KITTI-map and demo worlds: wrong attempts averaged 0.065-0.110, right fixes 0.245-0.473, "
        "and the final inliers of whole runs 0.24-0.42",
    )
    fix_revoke_below_fraction: float = Field(
        default=0.4,
        ge=0,
        le=1,
        description="the fix is revoked when, once fix_min_inliers submaps have come since it, fewer than this "
        "fraction of them have an accepted loop closure (measured with planted wrong fixes on the KITTI 00 / 09 "
        "worlds: right fixes kept >= 44 %, wrong ones fell below 40 % within 6-8 submaps; 0.5 revoked a right one)",
    )
    fix_revoke_after_refutations: int = Field(
        default=2,
        ge=1,
        description="the fix is revoked when this many submaps in a row find it refuted (fix_revoke_below_fraction); "
        "at the earlier ones the online estimate is withheld and nothing is anchored or committed. KITTI 09 at seeds "
        "0-7 revoked its right fix in 7 runs with 1 and in 4 with 2 (with online_gate_release_submaps 3); a real "
        "wrong fix on KITTI 02 showed the same worst error either way",
    )
    commit_accepted_inliers: bool = Field(
        default=True, description="after the fix, drop the alternatives of submaps that have an inlier"
    )
    commit_delay_submaps: int = Field(
        default=2, ge=0, description="the most recent submaps keep their alternatives (reference delay)"
    )
    online_gate_chi2: float | None = Field(
        default=7.81,
        gt=0,
        description="after the fix, a new loop closure whose innovation against the online prediction at its frame "
        "(squared Mahalanobis distance of x, y, yaw under the prediction's covariance plus the loop-closure prior's) "
        "exceeds this is held out of the online pose graph, until closures of online_gate_release_submaps or more "
        "submaps fail it at once (then the prediction may be what is wrong, and they are all taken); default: "
        "chi-square 95 % with 3 degrees of freedom (a held right closure costs one submap's delay, a taken wrong one "
        "metres); null: no gate",
    )
    online_gate_release_submaps: int = Field(
        default=3,
        ge=1,
        description="closures of this many submaps failing the online gate at once are all taken. Submaps after the "
        "fix overlap (20 m apart, 40 m radius) and share primitives, so two neighbours can be wrong together: on "
        "KITTI 09 two such closures, 9.1 and 6.6 m off, took the estimate 5-6 m off under 2",
    )
    online_window_submaps: int | None = Field(
        default=100,
        ge=1,
        description="after the fix, the online consistency graph holds only the candidates of the last this many "
        "submaps; older accepted loop closures stay in the pose graph. The consistency gates widen with the path "
        "between two submaps, so a submap this far back agrees with nearly every candidate and adds cost, not "
        "information; the window keeps the cost per submap from growing with the drive (null: the whole drive)",
    )
    final_rematch: bool = Field(
        default=True, description="finalize: re-match every submap with the rotation prior near the trajectory (pass 2)"
    )
    covariance: bool = Field(default=True, description="compute the per-pose marginal covariance of the final graph")
    sanity_max_off_map_fraction: float = Field(
        default=0.1, ge=0, le=1, description="sanity gate: a final trajectory with more of its frames outside the "
        "aerial map (grown by sanity_off_map_margin_m) is reported as not localized"
    )
    sanity_off_map_margin_m: float = Field(default=50.0, ge=0, description="sanity gate: margin around the map")
    sanity_inlier_residual_m: float = Field(
        default=10.0, gt=0, description="sanity gate: a loop closure the final trajectory misses by more (5 prior sigmas) ..."
    )
    sanity_inlier_residual_deg: float = Field(default=25.0, gt=0, description="... or by more than this yaw")
    sanity_max_inlier_disagreement: float = Field(
        default=0.5, ge=0, le=1, description="sanity gate: a final trajectory missing more of its own loop closures "
        "is reported as not localized"
    )
    sanity_heading_window_m: float = Field(default=100.0, gt=0, description="sanity gate: path window of the heading test")
    sanity_max_heading_bend_deg: float = Field(
        default=60.0, gt=0, description="sanity gate: a final trajectory turning the odometry's heading by more within "
        "the window (far beyond any odometry drift) is reported as not localized"
    )
