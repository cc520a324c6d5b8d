"""Validated configuration of the matching stage. Only pydantic is imported here."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from meridian_torch.config.base import StrictModel

__all__ = ["ClipperConfig"]


class ClipperConfig(StrictModel):
    """Parameters of `solve_clipper`; the defaults are CLIPPER v0.2.4's `clipper::Params`.

    The reference's `tol_Fop` is not offered because the reference never reads it, and
    `affinityeps` belongs to building the affinity matrix, not to solving it.
    """

    tol_u: float = Field(default=1e-8, gt=0, description="inner loop stops when ||u+ - u|| < tol_u")
    tol_F: float = Field(default=1e-9, gt=0, description="... or when |F+ - F| < tol_F")
    max_inner_iterations: int = Field(
        default=200, ge=1, description="projected-gradient steps per penalty value d"
    )
    max_outer_iterations: int = Field(
        default=1000, ge=1, description="penalty (d) increases before giving up"
    )
    beta: float = Field(default=0.25, gt=0, lt=1, description="backtracking factor of the line search")
    max_line_search_iterations: int = Field(
        default=99, ge=1, description="line-search trials per gradient step"
    )
    eps: float = Field(
        default=1e-9,
        gt=0,
        description="numerical zero of the line-search test, the support test and the Cb*u test",
    )
    rescale_u0: bool = Field(default=True, description="apply one power step (M u0) to the start vector")
    initial_d: float | None = Field(
        default=None,
        ge=0,
        description="start value of the penalty weight d; None = CLIPPER's data-driven mean of "
        "(Mu)_i / (Cb u)_i",
    )
    diagonal: Literal["identity", "input"] = Field(
        default="identity",
        description="'identity' replaces diag(M) by ones (CLIPPER C++); 'input' keeps it as unary "
        "weights (CLIPPER MATLAB)",
    )
    rounding: Literal["clipper", "support", "densest"] = Field(
        default="clipper",
        description="'clipper' = round(F) largest entries of u (reference DSD_HEU, loses recall on "
        "weighted cliques); 'support' = u_i > support_threshold * max(u); 'densest' = exact densest "
        "subgraph of the support",
    )
    support_threshold: float = Field(
        default=0.0,
        ge=0,
        lt=1,
        description="relative threshold defining the support of u for 'support' and 'densest'; "
        "0 = CLIPPER's NONZERO",
    )
    densest_max_exact: int = Field(
        default=50,
        ge=1,
        description="largest support solved exactly by 'densest' (an LP with ~s^2/2 variables, ~0.2 s "
        "at s = 50); larger supports fall back to greedy peeling, a 1/2-approximation",
    )
    seed: int = Field(
        default=0, ge=0, description="seed of the random start when neither u0 nor a generator is given"
    )


class AssociationConfig(StrictModel):
    """Putative associations (`putative_associations`); reference `PrimitiveMatchParams`."""

    k_prim: int = Field(default=20, ge=1, description="K_prim: semantic neighbours taken per primitive")
    direction: Literal["ground_to_aerial", "union"] = Field(
        default="ground_to_aerial",
        description="'ground_to_aerial' = k aerial neighbours per ground primitive (reference knn_direction "
        "'2to1'); 'union' also adds k ground neighbours per aerial primitive, deduplicated",
    )
    min_line_length_m: float = Field(
        default=2.0, ge=0, description="segments shorter than this are dropped on both sides; rays/infinite kept"
    )


class AffinityConfig(StrictModel):
    """Scoring of the data-association affinity M_DA (`matching.affinity`).

    Defaults are the reference `PrimitiveMatchParams` (paper values sigma_t = 2 m,
    sigma_theta = 20 deg with eps = sigma).
    """

    sigma_t_m: float = Field(default=2.0, gt=0, description="sigma of the distance-difference kernel")
    epsilon_t_m: float = Field(default=2.0, gt=0, description="distance differences above this score 0")
    sigma_theta_deg: float = Field(
        default=20.0, gt=0, lt=90, description="sigma of the angle-difference kernel; tan(sigma) scales lever arms"
    )
    epsilon_theta_deg: float = Field(default=20.0, gt=0, description="angle differences above this score 0")
    min_point_separation_m: float = Field(
        default=3.0, ge=0, description="point pairs closer than this in either map are never consistent"
    )
    min_line_angle_deg: float = Field(
        default=10.0,
        ge=0,
        description="line pairs more parallel than this are 'near-parallel' (see parallel_line_pairs)",
    )
    parallel_line_pairs: Literal["reject", "separation"] = Field(
        default="separation",
        description="near-parallel line pairs: 'reject' = never consistent (reference); 'separation' = "
        "consistent when both maps' pairs are near-parallel, scored by the angle kernel times the "
        "distance kernel of the perpendicular separation of the two infinite lines (unsigned without a "
        "rotation prior, per axis with one; sigma inflated by sin(angle) * the along-line offset of the "
        "reference points; separations below min_point_separation_m score 0). Pairs near-parallel in "
        "one map only score 0. Measured with scripts/exp_registration.py (each submap against its true "
        "patch, < 5 m / 5 deg, mean of seeds 0-2, top-1/5/25 known rotation | top-25 unknown, reject -> "
        "separation): demo world 22 submaps 9/20/20 | 3 -> 20/38/39 | 18; KITTI 09 (all 477 frames, 28 "
        "submaps) 6/12/12 | 4 -> 7/12/12 | 7; simulated KITTI 00 (9 submaps) 4/22/26 | 0 -> "
        "22/44/44 | 7. Not worse anywhere and about twice as good on two of three worlds, hence the default (a "
        "departure from the paper; 'reject' reproduces it)",
    )
    cosine_min: float = Field(default=0.1, description="descriptor cosine at or below this kills an association")
    cosine_max: float = Field(default=0.5, description="cosine at or above this gives the full unary score 1")
    rotation_uncertainty_deg: float = Field(
        default=20.0, ge=0, lt=90, description="remaining heading uncertainty of a rotation prior"
    )
    lever_arm_inflation: bool = Field(
        default=True, description="inflate sigma_t by tan(sigma_theta) * lever arm for points derived from lines"
    )
    affinity_eps: float = Field(default=1e-4, ge=0, description="affinities at or below this are set to 0")
    dense_max_m: int = Field(
        default=256,
        ge=1,
        description="`affinity` returns a dense (P, m, m) tensor up to this m, sparse COO above. Both are built "
        "from the same gated non-zero list (~3.5 % of the pairs at m = 2000); the particle sampler converts to "
        "sparse and prunes anyway, and a dense batch costs P m^2 4 bytes (400 MB at P = 25, m = 2000)",
    )
    block_pairs: int = Field(
        default=1 << 20,
        ge=1,
        description="association pairs gated per row block (bounds peak memory). Measured on 2 loaded cores, "
        "P = 25, m = 2000: 2^20 took 1.4 s, 2^18 and 2^16 were 10-60x slower (per-op overhead and thread "
        "synchronisation dominate small blocks)",
    )

    def model_post_init(self, context: object, /) -> None:
        if self.cosine_max <= self.cosine_min:
            raise ValueError(f"cosine_max ({self.cosine_max}) must exceed cosine_min ({self.cosine_min})")


__all__ += ["AssociationConfig", "AffinityConfig"]


class ParticleConfig(StrictModel):
    """Langevin particle sampler of a distribution over inlier sets (`matching.particles`).

    Dynamics, preconditioner, early stopping and rounding follow the reference's
    `LangevinMatcherParams`. The reference runs 1000 particles x 1000 iterations on a GPU; the
    defaults here are sized for a CPU (see `n_particles` / `n_iterations` for the measurement).
    """

    n_particles: int = Field(
        default=256,
        ge=1,
        description="particles per patch (reference 1000, sized for a GPU). Measured on the demo world's rendered "
        "submaps against their true patch (scripts/exp_registration.py, 24 submaps, about 2 % true "
        "associations): known rotation top-1/25 = 17/58 % with 32 particles, 25/83 % with 128, 37/83 % with "
        "256, 29/83 % with 512; unknown rotation top-25 33 / 54 / 54 / 54 %; matching time 7.8 / 9.5 / 10.6 / "
        "13.1 s for all variants. An earlier sweep on planted scenes with 35-70 % inliers had found 32 enough: "
        "real submaps are much harder",
    )
    n_iterations: int = Field(
        default=100,
        ge=2,
        description="maximum Langevin steps (reference 1000); also the length of the noise annealing schedule. "
        "Same sweep: 50 steps still found the planted sets but put less mass on them (hard scene 0.16 vs 0.22). On "
        "rendered KITTI 00 / 09 submaps 50 steps lost 15-26 points of known-rotation top-25 registration success "
        "(scripts/exp_registration.py; why: matching/particles.py)",
    )
    max_associations: int | None = Field(
        default=128,
        ge=2,
        description="associations per patch given to the sampler: the best supported by the two-step walk "
        "count M'(M'1) (`support_pruning`); None = all. Cuts the cost per step ~(m / k)^2 and, by removing "
        "clutter, raised the particle mass on the true set (planted 70 % scene, 32 x 100: 0.95 at k = 128, "
        "0.63 at 256; 64 x 200 without pruning at m = 2000: 0.08); 81-89 % of the true associations rank in "
        "the top 128 of 2000 (the rest are not needed for the pose). 96 or 64 were not better on rendered KITTI 00 / "
        "09 submaps (64: 7 points less known-rotation top-1 on KITTI 00, mean of 10 seeds)",
    )
    step_size: float = Field(default=1.0, gt=0, description="eta; the noise scale is sqrt(eta)")
    rmsprop: bool = Field(default=True, description="RMSprop-style preconditioner (the reference's 'adagrad')")
    alpha: float = Field(default=0.9, ge=0, lt=1, description="decay of the preconditioner's squared-step average")
    anneal: bool = Field(default=True, description="noise decays linearly from sqrt(eta) to 0 over n_iterations")
    noise: bool = Field(default=True, description="False = pure projected preconditioned ascent")
    early_stop: bool = Field(default=True, description="stop a patch once its mean objective has settled")
    check_interval: int = Field(default=10, ge=1, description="iterations between convergence checks")
    obj_tol: float = Field(default=1e-5, ge=0, description="relative change of the EMA objective counted as settled")
    patience: int = Field(default=3, ge=1, description="consecutive settled checks that stop a patch")
    min_set_size: int = Field(default=3, ge=1, description="rounded sets smaller than this are discarded")
    rounding: Literal["clipper", "support"] = Field(
        default="clipper",
        description="'clipper' = the round(x'M_d x) largest entries (reference; drops members of weighted "
        "cliques, e.g. 9 of a 10-clique of affinity 0.9); 'support' = every entry x_i > 0",
    )
    seed: int = Field(default=0, ge=0, description="seed of the sampler when no generator is given")


__all__ += ["ParticleConfig"]


class CoarseSearchConfig(StrictModel):
    """The weight-free coarse global search (`matching.place_recognition.coarse`): per-class raster
    maps of the primitives correlated with the whole aerial map over yaws by FFT, chained over
    successive submaps by odometry."""

    cell_m: float = Field(default=2.0, gt=0, description="raster cell size of map and submap")
    radius_m: float = Field(default=40.0, gt=0, description="submap disk around its centre that is correlated")
    yaws: int = Field(default=36, ge=1, description="yaw grid of T_world_odom over [0, 2 pi)")
    classes: int = Field(
        default=1,
        ge=1,
        description="descriptor clusters rasterised as separate grids (1 = geometry only). Measured on the "
        "KITTI 09 (7 Hz) world's first 16 submaps, single submaps: 4 classes and 1 class both rank the true "
        "patch at chance or worse (see README, coarse search)",
    )
    orientation_bins: int = Field(
        default=4,
        ge=0,
        description="line samples go to one raster per orientation bin over [0, pi) (0 = points and lines "
        "share one raster); points always have their own raster when > 0. KITTI 09 (7 Hz) world, first 16 "
        "submaps, chain ranks of the true patch among 609: with 0 bins at chance throughout; with 4 bins "
        "they fall to 63, 57, 37, 13, 4 over the last five submaps (8 bins: 53, 43, 14, 10, 2 at 1.8x "
        "the cost). 4 m cells lose it (ranks 104-40)",
    )
    blur_cells: float = Field(default=1.0, ge=0, description="Gaussian blur sigma of both rasters, cells")
    min_window_energy: float = Field(
        default=1.0,
        ge=0,
        description="cells whose map window has less energy (sum of squared deviations of the blurred "
        "occupancy; one isolated blurred point has about 1 / (4 pi blur^2)) score 0: near-empty windows "
        "correlate perfectly with anything",
    )
    chain_decay: float = Field(
        default=0.9, ge=0, le=1, description="weight of the previous submaps' chain volume (0 = single submaps)"
    )
    chain_slack_m: float = Field(
        default=2.0, ge=0, description="odometry drift allowed between successive submaps (max-pool radius)"
    )
    seed: int = Field(default=0, ge=0, description="seed of the descriptor clustering")


class PlaceRecognitionConfig(StrictModel):
    """Which aerial patches a ground submap is matched against."""

    mode: Literal["auto", "global", "exhaustive", "near", "coarse"] = Field(
        default="auto",
        description="'global': top k_global patches by descriptor similarity (paper); 'exhaustive': every patch; "
        "'auto': exhaustive on maps of at most exhaustive_max_patches patches, else coarse; 'near': the patches "
        "overlapping most with a disk around a predicted position; 'coarse': top k_coarse patches of the coarse "
        "search (`coarse`). Default auto, not the paper's global: cross-view "
        "place recognition with the classical descriptors ranks the true patch at random (demo world: median rank "
        "45 of 81), and without the true patch no submap can register; on the demo map exhaustive matching is "
        "what lets the localizer fix at all (measured: ATE 0.7 m vs a wrong fix with global)",
    )
    exhaustive_max_patches: int = Field(
        default=1000,
        ge=0,
        description="'auto' matches every patch up to this map size (about 1 km x 1 km at 60 m / 50 %). "
        "Matching time before the fix grows linearly with it, about 0.08 s per patch and submap on 2 cores "
        "(KITTI 09 world, 609 patches: 48 s per submap); after the fix only 'near' patches are matched. "
        "Measured on the full KITTI 00 / 09 worlds against global top-25: KITTI 09 gets a fix (none with "
        "global), KITTI 00 fixes after 280 m instead of 530 m with final ATE 1.2 m instead of 1.4 m; the "
        "real-time factor falls from 0.93 to 0.58 (KITTI 00) and 0.57 to 0.32 (KITTI 09). Lower it when a "
        "global describer that ranks the true patch well is used (AnyLoc) or real time matters more",
    )
    k_global: int = Field(default=25, ge=1, description="K_global: patches per submap in 'global' mode (paper)")
    k_coarse: int = Field(default=25, ge=1, description="patches per submap in 'coarse' mode")
    coarse: CoarseSearchConfig = Field(default_factory=CoarseSearchConfig)
    near_radius_m: float = Field(default=25.0, gt=0, description="disk radius around the predicted position, 'near' mode")
    near_patches: int = Field(default=2, ge=1, description="patches kept in 'near' mode (largest overlap first)")


__all__ += ["CoarseSearchConfig", "PlaceRecognitionConfig"]


class RegistrationConfig(StrictModel):
    """Weights and thresholds of `register_se2` (thresholds are the reference's `RegisterParams`)."""

    line_direction_weight: float = Field(
        default=25.0,
        ge=0,
        description="weight (m^2) of sin^2(line angle error) against a squared offset of 1 m. A segment of "
        "length L scored by the point-to-line distances of its two endpoints weighs its direction by "
        "(L/2)^2, so 25 m^2 stands for ~10 m lines. The reference's Arun cross-covariance implies 1 m^2, "
        "which under-weights directions: on noisy synthetic sets (0.3 m endpoint noise) 25 m^2 cut the p90 "
        "rotation error of lines-only sets from 2.8 to 1.8 deg and never did worse",
    )
    information_eps: float = Field(
        default=0.05,
        ge=0,
        description="a set is degenerate unless both the rotation information (weight * m^2) and the "
        "smallest translation information (weight) exceed this (the reference's eps)",
    )
    ambiguity_eps: float = Field(
        default=0.05,
        ge=0,
        description="a set is ambiguous unless the second-best rotation costs this much more "
        "(weight * m^2; the reference's dup_eps)",
    )
    n_angle_samples: int = Field(
        default=32, ge=8, description="grid over [-pi, pi) that brackets the minima of f(θ)"
    )
    newton_iterations: int = Field(default=10, ge=1, description="bracketed Newton steps per minimum")


__all__ += ["RegistrationConfig"]


class VerificationConfig(StrictModel):
    """Geometric verification of hypotheses (`matching.verification`, not in the paper).

    Measured on the demo world's 24 rendered submaps against their true patch (scripts/
    exp_registration.py, 256 particles, seed 0): ranking the 50 heaviest clusters by mass x alignment
    instead of mass alone gave unknown-rotation top-1 / 25 = 29 / 54 % instead of 12 / 54 %, known
    rotation 42 / 83 % instead of 37 / 83 %. The tolerances are first choices (the matching sigmas'
    scale), not tuned. Scoring ground lines in pieces of at most 4 m, each graded by closeness,
    instead of whole lines all-or-nothing: demo top-1 (mean of seeds 0-2) 35 -> 40 % known
    rotation, 26 -> 32 % unknown; in the demo run the final pass's top-1 50 -> 67 % of submaps at
    the same final ATE (0.64 -> 0.67 m; ungraded pieces: 63 % but 0.82 m); +6 % matching time
    (2 m pieces: same quality, +22 %). Full KITTI worlds with every patch matched before the fix
    (scripts/exp_localization.py): the same fixes; final-pass top-1 45 -> 46 % (00) and
    40 -> 47 % (09); ATE online / final 1.73 / 1.17 -> 1.63 / 1.23 m (00), 2.70 / 0.94 ->
    2.18 / 0.85 m (09). The cost: with top-25 place recognition instead (exhaustive_max_patches=128)
    the KITTI 00 world gets no fix, where whole lines got one after 530 m.
    """

    enabled: bool = Field(
        default=True, description="rank hypotheses by particle mass x alignment (false: mass only, the paper)"
    )
    candidates: int = Field(
        default=50, ge=1, description="clusters per patch verified (heaviest first); at least hypotheses_per_patch"
    )
    line_piece_m: float = Field(
        default=4.0, gt=0, description="ground lines are scored in equal pieces of at most this length"
    )
    line_distance_m: float = Field(
        default=1.5, gt=0,
        description="a ground line piece counts less the farther its midpoint lies from an aerial line, nothing beyond this",
    )
    line_angle_deg: float = Field(default=10.0, gt=0, le=90, description="only aerial lines within this angle of the piece count")
    point_distance_m: float = Field(
        default=2.0, gt=0, description="a ground point counts less the farther it lies from an aerial point, nothing beyond this"
    )
    point_weight_m: float = Field(default=5.0, ge=0, description="a point exactly on an aerial point counts as this much line length")
    chunk_pairs: int = Field(
        default=8_000_000,
        ge=1,
        description="(pose, ground primitive, aerial primitive) triples evaluated at once; bounds memory to "
        "about 10 bytes per triple",
    )


__all__ += ["VerificationConfig"]


class MatchConfig(StrictModel):
    """Everything matching needs: patch selection, associations, affinity, the inlier-set solver, clustering."""

    place_recognition: PlaceRecognitionConfig = Field(default_factory=PlaceRecognitionConfig)
    associations: AssociationConfig = Field(default_factory=AssociationConfig)
    affinity: AffinityConfig = Field(default_factory=AffinityConfig)
    particles: ParticleConfig = Field(default_factory=ParticleConfig)
    clipper: ClipperConfig = Field(default_factory=ClipperConfig)
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    solver: Literal["particles", "clipper"] = Field(
        default="particles",
        description="'particles' = distribution over inlier sets (paper); 'clipper' = one densest set per patch, "
        "reported as a single hypothesis with probability 1",
    )
    patch_chunk: int = Field(
        default=8,
        ge=1,
        description="patches whose affinities are built together (bounds peak memory; results do not depend on "
        "it). Their pruned problems are sampled in one batch with those of the other chunks. Bench case (25 "
        "patches, m = 2000, 1 thread): the sparse affinity of all 25 at once raised the peak by ~370 MB",
    )
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    hypotheses_per_patch: int = Field(default=25, ge=1, description="L, clustered hypotheses kept per patch")
    cluster_translation_m: float = Field(default=1.0, gt=0, description="cluster radius in translation")
    cluster_rotation_deg: float = Field(default=5.0, gt=0, description="cluster radius in yaw")


__all__ += ["MatchConfig"]
