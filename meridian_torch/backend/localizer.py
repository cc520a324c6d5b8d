"""Incremental and offline cross-view localization.

States, per new ground submap:
- "pre" (no global fix yet): match the submap against its place-recognition patches with free
  rotation, pool its candidates, CLIPPER on the pool. With >= `attempt_min_inliers` inliers (and
  at least `fix_min_inliers` submaps, else the gate cannot hold) an **attempt** follows: pose graph
  on the pool's inliers -> rough trajectory -> re-match every submap so far against the patches
  near its rough position with the rotation prior -> CLIPPER on these fresh candidates. The fix is
  **committed** when they give >= `fix_min_inliers` inliers making up >= `fix_min_inlier_fraction`
  of the submaps so far, with a mean hypothesis probability >= `fix_min_mean_probability`: the
  fresh candidates replace the pool, state "post". A failed attempt
  leaves the pool untouched.
- "post": the submap is matched with the rotation prior against the patches near its pose
  predicted from the last optimized pose carried forward by odometry; its candidates join the
  pool; CLIPPER + pose graph; accepted inliers are committed (the other candidates of their
  submaps are dropped, except for the `commit_delay_submaps` most recent submaps).
- The fix is checked by the submaps that follow it: once `fix_min_inliers` submaps have come
  since the fix, fewer than `fix_revoke_below_fraction` of them with an accepted loop closure
  refutes it (a wrong fix finds few consistent matches near its wrong prediction; a right one,
  most). The online estimate is withheld from a refuting submap on (NaN), and nothing is
  anchored or committed; the next submap that does not refute it brings the estimate back.
  `fix_revoke_after_refutations` refuting submaps in a row **revoke** it: back to "pre", the pool
  is rebuilt from the submaps' place-recognition candidates and the next fix must pass the gate
  over every submap again.

The online pose graph lives in iSAM2 from the fix on (`IncrementalPoseGraph`: each update adds
the new frames and the changed loop closures). The online estimate at a frame = the anchor (last
optimized pose of the latest update available at that frame's time) carried forward by odometry.
`finalize` solves the final pool once more over every frame and, with `final_rematch`, re-matches
every submap with the rotation prior near that trajectory (offline pass 2), keeping pass 2 when
it passes the fix gate.

Positions are worked in the aerial map's frame (world minus `aerial_map.local_origin_xy`, small
numbers that float32 matching keeps exact); every result is returned in world coordinates
(float64), whatever the size of the georeference's coordinates.

Output poses are SE(3): the optimized planar correction T_world_odom(t) (x, y, yaw) composed
with the full odometry pose, so z, roll and pitch are the odometry's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Literal

import numpy as np
import torch

from meridian_torch.backend.candidates import LoopClosureCandidates
from meridian_torch.backend.consistency import (
    Edges,
    InlierSelection,
    select_inliers,
    select_inliers_in_windows,
)
from meridian_torch.backend.frames import FrameBuffer, OnlineUpdate, lift_se2
from meridian_torch.backend.pose_graph import (
    IncrementalPoseGraph,
    PoseGraphSolution,
    closure_sigma_scales,
    optimize_pose_graph,
    propagate_covariance,
)
from meridian_torch.backend.results import LocalizationResult, LocalizerEvent, Matcher, StageSeconds
from meridian_torch.backend.sanity import sanity_problems
from meridian_torch.backend.submap_matching import SubmapMatching
from meridian_torch.config import MeridianConfig
from meridian_torch.core.timing import stage
from meridian_torch.errors import ConfigError
from meridian_torch.geometry.planar import wrap_angle, yaw_of
from meridian_torch.geometry.trajectory import Trajectory
from meridian_torch.matching.match import match_submap
from meridian_torch.matching.place_recognition import reads_global_descriptors
from meridian_torch.runtime import release_free_memory
from meridian_torch.types import AerialMap, GroundSubmap

__all__ = ["Localizer", "localize_offline"]


def _check_global_descriptors(aerial_map: AerialMap, cfg: MeridianConfig) -> None:
    """Refuse a place recognition that would compare the frames' global descriptors with a map's
    made by another back end (their similarities would mean nothing)."""
    pr = cfg.matching.place_recognition
    map_backend = aerial_map.global_descriptor_backend
    run_backend = cfg.perception.global_descriptor.backend
    if map_backend is None or map_backend == run_backend or not reads_global_descriptors(pr, len(aerial_map), map_backend):
        return
    raise ConfigError(
        f"perception.global_descriptor.backend is '{run_backend}', but the aerial map's global descriptors were "
        f"made by '{map_backend}', and place recognition ('{pr.mode}', global_fusion '{pr.global_fusion}') compares "
        "the two: use the map's back end, rebuild the map with this one, or set "
        "matching.place_recognition.global_fusion: never"
    )


class Localizer:
    """Cross-view localizer over one sequence; feed submaps in order with `add_submap`.

    Args:
        aerial_map: the aerial map (patches, primitives in world metres, global descriptors).
        cfg: the full config (`matching` for matching and patch selection, `backend` here).
        odometry: T_odom_base over time; must cover `frame_times`.
        frame_times: (N,) strictly increasing frame timestamps; one pose-graph node per frame.
            Without `odometry` and `frame_times` the frames come one batch at a time through
            `add_frames` (a robot's live input); the results are the same as with all given here.
        seed: seeds matching and CLIPPER (default `cfg.matching.particles.seed`); one seed gives
            identical results.
        incremental: False = offline mode: `add_submap` only matches with place recognition and
            pools; everything is solved in `finalize` (pass 1 + pass 2).
        matcher: the matching function (default `match_submap`; tests may inject their own).
        online_covariance: also compute the marginal covariance of every online update's anchor
            frame (one more GTSAM factorization per update), for `latest_estimate`.
    """

    def __init__(
        self,
        aerial_map: AerialMap,
        cfg: MeridianConfig,
        odometry: Trajectory | None = None,
        frame_times: np.ndarray | None = None,
        *,
        seed: int | None = None,
        incremental: bool = True,
        matcher: Matcher | None = None,
        online_covariance: bool = False,
    ) -> None:
        if cfg.matching.place_recognition.mode == "near":
            raise ConfigError(
                "matching.place_recognition.mode: 'near' needs a pose estimate; use 'auto', 'coarse', 'global' or "
                "'exhaustive' for localization (the localizer switches to 'near' by itself after the fix)"
            )
        _check_global_descriptors(aerial_map, cfg)
        if (odometry is None) != (frame_times is None):
            raise ValueError("give both odometry and frame_times, or neither (frames then come through add_frames)")
        self.aerial_map = aerial_map
        self.cfg = cfg
        self._frames = FrameBuffer()
        if frame_times is not None:
            frame_times = np.asarray(frame_times, dtype=np.float64)
            if frame_times.ndim != 1 or len(frame_times) == 0:
                raise ValueError("frame_times must be a non-empty 1-D array")
            if not odometry.covers(frame_times):
                raise ValueError("the odometry does not cover the frame times")
            self.add_frames(frame_times, odometry.interpolate(frame_times))
        self.incremental = incremental
        self.online_covariance = online_covariance
        seed = cfg.matching.particles.seed if seed is None else seed
        self._timer = StageSeconds()
        self._matching = SubmapMatching(aerial_map, cfg, matcher or match_submap, seed, self._timer)
        self._clipper_generator = torch.Generator().manual_seed(seed)
        self._local_origin_xy = tuple(float(v) for v in aerial_map.local_origin_xy)
        self.submaps: list[GroundSubmap] = []
        self._nodes: list[int] = []  # pose-graph node (frame) of every submap
        self.submap_hypotheses: dict[int, LoopClosureCandidates] = {}
        self.submap_matching_mode: dict[int, str] = {}
        self.pool = LoopClosureCandidates.empty()
        # accepted loop closures of submaps older than `backend.online_window_submaps`: out of the
        # online consistency graph, still in the pose graph
        self.archive = LoopClosureCandidates.empty()
        self._pool_edges: tuple[int, Edges] | None = (
            None  # consistency graph of the pool's first n candidates
        )
        self.state: Literal["pre", "post"] = "pre"
        self._updates: list[OnlineUpdate] = []
        self._online_graph = IncrementalPoseGraph(cfg.backend)  # started at the fix
        self._anchored: dict[int, np.ndarray] = {}  # submap -> the loop closure (3, 3) in the online graph
        self.fix_submap_index: int | None = None
        self.fix_time: float | None = None
        self._fix_position = 0  # submaps added before the fix submap
        self._refutations = 0  # checks in a row that refuted the fix
        self.events: list[LocalizerEvent] = []
        # (pre-fix inlier indices, submaps re-matched, their candidates) of the last fix attempt
        self._attempt_cache: tuple[tuple[int, ...], int, LoopClosureCandidates] | None = None

    @property
    def frame_times(self) -> np.ndarray:
        """(N,) times of the frames so far (one pose-graph node each)."""
        return self._frames.times

    @property
    def T_odom_base(self) -> np.ndarray:
        """(N, 4, 4) odometry poses of the frames so far."""
        return self._frames.T_odom_base

    @property
    def _odom_se2(self) -> np.ndarray:
        return self._frames.odom_se2

    def add_frames(self, frame_times: np.ndarray, T_odom_base: np.ndarray) -> None:
        """Append frames (K,) strictly increasing times after the last frame's, (K, 4, 4) odometry poses."""
        frame_times = np.asarray(frame_times, dtype=np.float64).reshape(-1)
        T_odom_base = np.asarray(T_odom_base, dtype=np.float64).reshape(-1, 4, 4)
        if len(T_odom_base) != len(frame_times):
            raise ValueError(f"{len(frame_times)} frame times but {len(T_odom_base)} odometry poses")
        if not (np.isfinite(frame_times).all() and np.isfinite(T_odom_base).all()):
            raise ValueError("frame times and odometry poses must be finite")
        previous = self.frame_times[-1:]
        if np.any(np.diff(np.concatenate([previous, frame_times])) <= 0):
            raise ValueError("frame times must be strictly increasing (and after the previous frames')")
        self._frames.extend(frame_times, T_odom_base)

    # ------------------------------------------------------------------ matching
    def _node_of(self, t: float) -> int:
        k = int(np.searchsorted(self.frame_times, t))
        if k == len(self.frame_times) or (k > 0 and t - self.frame_times[k - 1] <= self.frame_times[k] - t):
            k -= 1
        return k

    def _rematch(self, T_world_base_nodes: np.ndarray, submaps: list[GroundSubmap]) -> LoopClosureCandidates:
        """Every submap matched near its pose in `T_world_base_nodes` (per node) with the rotation prior."""
        nodes = [self._node_of(s.time) for s in submaps]
        T_world_base = T_world_base_nodes[nodes]
        T_world_odom = T_world_base @ np.linalg.inv(self._odom_se2[nodes])
        priors = yaw_of(T_world_odom)
        patches = self._matching.near_patches(T_world_base[:, :2, 2])
        matched = []
        for submap, submap_patches, prior in zip(submaps, patches, priors):
            matched.append(self._matching.match(submap, submap_patches, float(prior)))
            release_free_memory()  # see the end of add_submap
        return LoopClosureCandidates.concat(matched)

    # ------------------------------------------------------------------ solving
    def _inliers(self, candidates: LoopClosureCandidates, *, in_windows: bool = False) -> InlierSelection:
        start = time.perf_counter()
        select = select_inliers_in_windows if in_windows else select_inliers
        with stage("consistency"):
            sel = select(candidates, self.cfg.backend, self._clipper_generator)
        self._timer.add("consistency", start)
        return sel

    def _pool_inliers(self) -> InlierSelection:
        """CLIPPER on the pool, scoring only the pairs of candidates appended since the last call."""
        start = time.perf_counter()
        with stage("consistency"):
            sel = select_inliers(
                self.pool, self.cfg.backend, self._clipper_generator, known_edges=self._pool_edges
            )
        self._pool_edges = (len(self.pool), sel.edges)
        self._timer.add("consistency", start)
        return sel

    def _set_pool(self, pool: LoopClosureCandidates, edges: Edges | None) -> None:
        self.pool = pool
        self._pool_edges = (len(pool), edges) if edges is not None else None

    def _gate(self, inliers: LoopClosureCandidates, n_submaps: int) -> bool:
        """The fix gate: enough inlier loop closures, for enough of the submaps, probable enough on
        average (a wrong fix is built from closures that each align little of their submap)."""
        b = self.cfg.backend
        n = len(inliers)
        if n < b.fix_min_inliers or n < b.fix_min_inlier_fraction * n_submaps:
            return False
        return b.fix_min_mean_probability is None or float(inliers.probability.mean()) >= b.fix_min_mean_probability

    def _optimize(
        self, inliers: LoopClosureCandidates, n_nodes: int, covariance: bool | Literal["last"] = False
    ) -> PoseGraphSolution:
        start = time.perf_counter()
        nodes, priors = self._prior_poses(inliers)
        with stage("pose graph"):
            sol = optimize_pose_graph(
                self._odom_se2[:n_nodes], nodes, priors, self.cfg.backend, covariance=covariance,
                prior_scales=self._prior_scales(inliers),
            )
        self._timer.add("pose_graph", start)
        return sol

    def _prior_poses(self, inliers: LoopClosureCandidates) -> tuple[np.ndarray, np.ndarray]:
        """Each loop closure's node (frame nearest its submap's time) and the planar pose it
        measures there: the measurement moved from the submap time to the node along the odometry."""
        nodes = np.array([self._node_of(float(t)) for t in inliers.time], dtype=np.int64)
        T_world_odom = inliers.T_world_base.numpy() @ np.linalg.inv(inliers.T_odom_base.numpy())
        return nodes, T_world_odom @ self._odom_se2[nodes]

    def _prior_scales(self, inliers: LoopClosureCandidates) -> np.ndarray:
        """Each loop closure's scale of the prior sigmas, from its hypothesis probability."""
        return closure_sigma_scales(inliers.probability.numpy(), self.cfg.backend)

    def _anchor(self, inliers: LoopClosureCandidates, n_nodes: int, available_time: float) -> None:
        """Update the online pose graph (iSAM2) to frame n_nodes - 1 and these inliers; its last
        pose anchors the online estimate from `available_time` on."""
        start = time.perf_counter()
        nodes, priors = self._prior_poses(inliers)
        self._anchored = dict(zip(inliers.submap_index.tolist(), priors))
        n_nodes = max(n_nodes, self._online_graph.n_nodes)
        with stage("pose graph"):
            T_world_base, cov = self._online_graph.update(
                self._odom_se2[:n_nodes], nodes, priors, covariance=self.online_covariance,
                prior_scales=self._prior_scales(inliers),
            )
        self._timer.add("pose_graph", start)
        last = n_nodes - 1
        self._updates.append(OnlineUpdate(available_time, T_world_base @ np.linalg.inv(self._odom_se2[last]), last, cov))

    def _prediction(self, update: OnlineUpdate, node: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The (3, 3) planar pose at frame `node` predicted by `update` (its anchor carried along the
        odometry, backwards for a frame before the anchor's) and its (3, 3) covariance of (x, y, yaw),
        world axes (`propagate_covariance`; None when the update has none)."""
        lo, hi = sorted((update.node, node))
        path = update.T_world_odom @ self._odom_se2[lo : hi + 1]
        path = path if node >= update.node else path[::-1]  # from the anchor frame to `node`
        cov = None if update.covariance is None else propagate_covariance(update.covariance, path, self.cfg.backend)
        return path[-1], cov

    def _gated(self, accepted: LoopClosureCandidates) -> LoopClosureCandidates:
        """`accepted` without the loop closures, new to the online graph, whose innovation against the
        latest update's prediction fails `backend.online_gate_chi2`; when closures of
        `online_gate_release_submaps` or more submaps fail it at once they are all kept (then the
        prediction may be what is wrong)."""
        b = self.cfg.backend
        update = self._latest_anchor()
        if b.online_gate_chi2 is None or update is None or not len(accepted):
            return accepted
        nodes, priors = self._prior_poses(accepted)
        submaps = accepted.submap_index.tolist()
        # The nominal closure noise, not a closure's scaled one: a less probable closure is not let
        # through more easily.
        prior_cov = np.diag([b.prior_trans_sigma_m**2, b.prior_trans_sigma_m**2, math.radians(b.prior_rot_sigma_deg) ** 2])
        fails = np.zeros(len(accepted), dtype=bool)
        for k, (submap, node, prior) in enumerate(zip(submaps, nodes, priors)):
            anchored = self._anchored.get(submap)
            if anchored is not None and np.allclose(anchored, prior):
                continue
            predicted, cov = self._prediction(update, int(node))
            e = np.array([*(prior[:2, 2] - predicted[:2, 2]), wrap_angle(yaw_of(prior) - yaw_of(predicted))])
            S = prior_cov if cov is None else prior_cov + cov
            fails[k] = float(e @ np.linalg.solve(S, e)) > b.online_gate_chi2
        if len({submaps[k] for k in np.flatnonzero(fails)}) >= b.online_gate_release_submaps:
            return accepted
        return accepted.select(torch.from_numpy(~fails))

    def _keep(self, keep: torch.Tensor) -> None:
        """Keep the pool's candidates `keep` (N,) bool, and the known edges between them."""
        edges = None
        if self._pool_edges is not None and self._pool_edges[0] == len(self.pool):
            i, j, v = self._pool_edges[1]
            both = keep[i] & keep[j]
            new_index = torch.cumsum(keep, 0) - 1
            edges = (new_index[i[both]], new_index[j[both]], v[both])
        self._set_pool(self.pool.select(keep), edges)

    def _commit(self, inliers: torch.Tensor) -> None:
        """Keep only the inlier of every submap that has one, except for the most recent submaps;
        then move the inliers of submaps past the online window to the archive."""
        latest = self.submaps[-1].index
        if self.cfg.backend.commit_accepted_inliers:
            committed = self.pool.submap_index[inliers]
            committed = committed[committed <= latest - self.cfg.backend.commit_delay_submaps]
            keep = ~(torch.isin(self.pool.submap_index, committed) & ~inliers)
            self._keep(keep)
            inliers = inliers[keep]
        window = self.cfg.backend.online_window_submaps
        if window is not None:
            old = self.pool.submap_index <= latest - window
            if bool(old.any()):
                self.archive = LoopClosureCandidates.concat([self.archive, self.pool.select(old & inliers)])
                self._keep(~old)

    def _accepted(self, sel: InlierSelection) -> LoopClosureCandidates:
        """The archived loop closures and the pool's inliers `sel`."""
        return LoopClosureCandidates.concat([self.archive, self.pool.select(sel.inliers)])

    def _attempt_candidates(self, sel: InlierSelection, n_nodes: int) -> LoopClosureCandidates:
        """Re-match every submap so far near the rough trajectory of the pre-fix inliers `sel`.

        The pre-fix pool only grows, so inlier indices identify the inlier set. When it equals the
        last failed attempt's, the rough poses of the earlier submaps are unchanged (the new frames
        only extend the graph's free tail), and so are their re-match candidates: only the new
        submaps are matched.
        """
        key = tuple(torch.nonzero(sel.inliers).flatten().tolist())
        rough = self._optimize(self.pool.select(sel.inliers), n_nodes)
        cached = self._attempt_cache
        if cached is not None and cached[0] == key:
            done, fresh = cached[1], cached[2]
            fresh = LoopClosureCandidates.concat(
                [fresh, self._rematch(rough.T_world_base, self.submaps[done:])]
            )
        else:
            fresh = self._rematch(rough.T_world_base, self.submaps)
        self._attempt_cache = (key, len(self.submaps), fresh)
        return fresh

    def _fix_refuted(self, sel: InlierSelection) -> bool:
        """The submaps since the fix, once `fix_min_inliers` of them have come: fewer than
        `fix_revoke_below_fraction` of them have an accepted loop closure."""
        b = self.cfg.backend
        since = len(self.submaps) - 1 - self._fix_position
        if since < b.fix_min_inliers:
            return False
        accepted = self._accepted(sel).submap_index
        agreeing = int(torch.unique(accepted[accepted > self.fix_submap_index]).numel())
        return agreeing < b.fix_revoke_below_fraction * since

    def _latest_anchor(self) -> OnlineUpdate | None:
        """The latest update that gave an estimate (not `withheld`)."""
        return next((u for u in reversed(self._updates) if not u.withheld), None)

    def _withhold(self, n_nodes: int, available_time: float) -> None:
        """Withhold the online estimate from `available_time` on (until the next anchor)."""
        self._updates.append(OnlineUpdate(available_time, np.full((3, 3), np.nan), n_nodes - 1, None))

    def _revoke(self, n_nodes: int, available_time: float) -> None:
        """Back to the global search: withhold the online estimate from `available_time` on and
        rebuild the pool from every submap's place-recognition candidates."""
        self.state = "pre"
        self.fix_submap_index = self.fix_time = None
        searched = [c for i, c in self.submap_hypotheses.items() if self.submap_matching_mode[i] == "place_recognition"]
        self._set_pool(LoopClosureCandidates.concat(searched) if searched else LoopClosureCandidates.empty(), None)
        self.archive = LoopClosureCandidates.empty()
        self._online_graph = IncrementalPoseGraph(self.cfg.backend)
        self._anchored = {}
        self._attempt_cache = None
        self._refutations = 0
        self._withhold(n_nodes, available_time)

    # ------------------------------------------------------------------ public API
    def add_submap(self, submap: GroundSubmap, available_time: float | None = None) -> LocalizerEvent:
        """Process one new submap; `available_time` = when it was complete (default its time).

        The online estimate of frames from `available_time` on uses the result of this call.
        """
        start = time.perf_counter()
        if not len(self.frame_times) or submap.time > self.frame_times[-1]:
            raise ValueError(f"submap {submap.index}: time {submap.time} after the last frame given to the localizer")
        if self.submaps and submap.time < self.submaps[-1].time:
            raise ValueError(f"submap {submap.index}: time {submap.time} before the previous submap's")
        available_time = float(submap.time if available_time is None else available_time)
        self.submaps.append(submap)
        self._nodes.append(self._node_of(submap.time))
        n_nodes = self._node_of(available_time) + 1
        attempted = committed = doubted = revoked = False
        if self.state == "pre":
            with stage("place recognition"):
                patches, yaw_priors = self._matching.place_recognition_patches(submap)
            new = self._matching.match(submap, patches, yaw_priors)
            self.submap_hypotheses[submap.index] = new
            self.submap_matching_mode[submap.index] = "place_recognition"
            self.pool = LoopClosureCandidates.concat([self.pool, new])
            sel = self._pool_inliers() if self.incremental else None
            n_inliers = sel.count if sel is not None else 0
            b = self.cfg.backend
            if (
                sel is not None
                and n_inliers >= b.attempt_min_inliers
                and len(self.submaps) >= b.fix_min_inliers
            ):
                attempted = True
                fresh = self._attempt_candidates(sel, n_nodes)
                sel2 = self._inliers(fresh)
                fix_inliers = fresh.select(sel2.inliers)
                if self._gate(fix_inliers, len(self.submaps)):
                    committed = True
                    self._set_pool(fresh, sel2.edges)
                    self.state = "post"
                    self.fix_submap_index, self.fix_time = submap.index, available_time
                    self._fix_position = len(self.submaps) - 1
                    self._anchor(fix_inliers, n_nodes, available_time)
                    self._commit(sel2.inliers)
                    n_inliers = sel2.count
        else:
            anchor = self._latest_anchor().T_world_odom
            predicted = anchor @ self._odom_se2[self._nodes[-1]]
            patches = self._matching.near_patches(predicted[None, :2, 2])[0]
            prior = float(yaw_of(anchor))
            new = self._matching.match(submap, patches, prior)
            self.submap_hypotheses[submap.index] = new
            self.submap_matching_mode[submap.index] = "rotation_prior"
            self.pool = LoopClosureCandidates.concat([self.pool, new])
            sel = self._pool_inliers()
            n_inliers = sel.count + len(self.archive)
            refuted = self._fix_refuted(sel)
            self._refutations = self._refutations + 1 if refuted else 0
            if refuted and self._refutations >= self.cfg.backend.fix_revoke_after_refutations:
                revoked = True
                self._revoke(n_nodes, available_time)
            elif refuted:  # neither anchored on nor committed: the accepted set is in doubt
                doubted = True
                self._withhold(n_nodes, available_time)
            elif n_inliers:
                self._anchor(self._gated(self._accepted(sel)), n_nodes, available_time)
                self._commit(sel.inliers)
        event = LocalizerEvent(
            submap_index=submap.index,
            time=float(submap.time),
            state=self.state,
            n_patches=len(patches),
            n_hypotheses=len(new),
            n_candidates=len(self.pool),
            n_inliers=n_inliers,
            attempted=attempted,
            fix_committed=committed,
            seconds=time.perf_counter() - start,
            fix_revoked=revoked,
            fix_doubted=doubted,
        )
        self.events.append(event)
        # matching's scratch arrays, freed between blocks that live on, would stay resident
        release_free_memory()
        return event

    def _update_of_frames(self) -> np.ndarray:
        """(N,) index of the online update each frame's estimate comes from (-1 before the first)."""
        update_times = np.array([u.available_time for u in self._updates])
        return np.searchsorted(update_times, self.frame_times, side="right") - 1

    def online_estimate(self) -> np.ndarray:
        """(N, 4, 4) T_world_base the system had online at every frame time (NaN before the fix and
        after a revoked one).

        Frames after the latest update use that update (carried forward by odometry).
        """
        out = np.full((len(self.frame_times), 4, 4), np.nan)
        if not self._updates:
            return out
        which = self._update_of_frames()
        anchors = np.stack([u.T_world_odom for u in self._updates])
        ok = which >= 0
        ok[ok] = np.isfinite(anchors[which[ok], 0, 0])  # a withheld update (refuting submap, revocation)
        out[ok] = lift_se2(anchors[which[ok]] @ self._odom_se2[ok], self.T_odom_base[ok])
        return self._to_world(out)

    def online_covariances(self) -> np.ndarray:
        """(N, 3, 3) covariance of (x, y, yaw), world axes, of `online_estimate` at every frame: its
        update's anchor-frame marginal carried along the odometry to the frame
        (`propagate_covariance`, as in `latest_estimate`). NaN before the fix and where the update
        has no covariance (without `online_covariance`). A frame before its update's anchor frame
        (only when updates came out of time order) is carried back along the same odometry."""
        out = np.full((len(self.frame_times), 3, 3), np.nan)
        if not self._updates:
            return out
        which = self._update_of_frames()
        for k in np.flatnonzero(which >= 0):
            update = self._updates[which[k]]
            if update.covariance is not None:
                out[k] = self._prediction(update, int(k))[1]
        return out

    def latest_estimate(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The online T_world_base (4, 4, world) at the latest frame and its (3, 3) covariance of
        (x, y, yaw) in world axes, or (None, None) before the fix and while the estimate is
        withheld (after a refuting submap or a revoked fix). The covariance is the anchor frame's
        marginal carried along the odometry since (`propagate_covariance`; None without
        `online_covariance`)."""
        update = self._updates[-1] if self._updates else None
        if update is None or update.withheld:  # before the fix, or withheld
            return None, None
        k = len(self.frame_times) - 1
        T = lift_se2(update.T_world_odom @ self._odom_se2[k : k + 1], self.T_odom_base[k : k + 1])
        return self._to_world(T)[0], self._prediction(update, k)[1]

    def _to_world(self, T_map_base: np.ndarray) -> np.ndarray:
        """(N, 4, 4) poses in the map frame -> world (float64; NaN rows stay NaN)."""
        T_world_base = np.array(T_map_base, dtype=np.float64)
        T_world_base[:, :2, 3] += self._local_origin_xy
        return T_world_base

    def finalize(self, progress: Callable[[str], None] | None = None) -> LocalizationResult:
        """Final solve over every frame (+ pass 2 re-match when `backend.final_rematch`)."""
        b = self.cfg.backend
        n = len(self.frame_times)
        n_sub = len(self.submaps)
        best: tuple[PoseGraphSolution, LoopClosureCandidates] | None = None
        fresh = LoopClosureCandidates.empty()
        sel = self._pool_inliers()
        n_accepted = sel.count + len(self.archive)
        if n_accepted:
            inliers = self._accepted(sel)
            sol = self._optimize(inliers, n)
            if self._gate(inliers, n_sub):
                best = (sol, inliers)
            if b.final_rematch:
                if progress:
                    progress(f"final pass: re-matching {n_sub} submaps with the rotation prior")
                fresh = self._rematch(sol.T_world_base, self.submaps)
                sel2 = self._inliers(fresh, in_windows=True)  # its graph is nearly complete: bounded
                inliers2 = fresh.select(sel2.inliers)
                if self._gate(inliers2, n_sub):
                    best = (self._optimize(inliers2, n), inliers2)
        rejected: list[str] = []
        if best is not None:
            sol, inl = best
            nodes, measured = self._prior_poses(inl)
            rejected = sanity_problems(lift_se2(sol.T_world_base, self.T_odom_base), self.aerial_map.patches.bounds_xy, b,
                                       T_solution_se2=sol.T_world_base, T_odom_se2=self._odom_se2,
                                       inlier_nodes=nodes, T_inlier_se2=measured)
        localized = best is not None and not rejected
        if localized:
            inliers = best[1]
            sol = self._optimize(inliers, n, covariance=b.covariance) if b.covariance else best[0]
            T_final = lift_se2(sol.T_world_base, self.T_odom_base)
            cov = sol.covariance
        else:
            inliers = LoopClosureCandidates.empty()
            T_final = np.full((n, 4, 4), np.nan)
            cov = None
        origin = self._local_origin_xy
        return LocalizationResult(
            frame_times=self.frame_times.copy(),
            T_world_base=self._to_world(T_final),
            covariance=cov,
            T_world_base_incremental=self.online_estimate(),
            localized=localized,
            inliers=inliers.translated(origin),
            fix_submap_index=self.fix_submap_index,
            fix_time=self.fix_time,
            submap_hypotheses={k: c.translated(origin) for k, c in self.submap_hypotheses.items()},
            submap_matching_mode=dict(self.submap_matching_mode),
            final_hypotheses=fresh.translated(origin),
            events=list(self.events),
            timings=dict(self._timer.seconds),
            rejected_because="; ".join(rejected) or None,
            covariance_incremental=self.online_covariances() if self.online_covariance else None,
        )


def localize_offline(
    aerial_map: AerialMap,
    cfg: MeridianConfig,
    odometry: Trajectory,
    frame_times: np.ndarray,
    submaps: list[GroundSubmap],
    *,
    seed: int | None = None,
    matcher: Matcher | None = None,
    progress: Callable[[LocalizerEvent], None] | None = None,
) -> LocalizationResult:
    """Offline localization: every submap against its place-recognition patches, then pass 1
    (CLIPPER + pose graph) and pass 2 (re-match with the rotation prior) in `finalize`."""
    loc = Localizer(aerial_map, cfg, odometry, frame_times, seed=seed, incremental=False, matcher=matcher)
    for submap in submaps:
        event = loc.add_submap(submap)
        if progress:
            progress(event)
    return loc.finalize()
