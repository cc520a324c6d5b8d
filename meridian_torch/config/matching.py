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

    The kernel defaults are the reference `PrimitiveMatchParams` (paper values sigma_t = 2 m,
    sigma_theta = 20 deg with eps = sigma); `parallel_line_pairs` departs from it ('reject' is the
    reference).
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
        description="near-parallel line pairs: 'reject' = never consistent (paper, reference); 'separation' = "
        "pairs near-parallel in both maps are scored by their perpendicular separation (`matching.affinity`), "
        "pairs near-parallel in one map only score 0",
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
        description="`affinity` returns a dense (P, m, m) tensor up to this many associations m, sparse COO "
        "above (a dense batch costs P m^2 4 bytes)",
    )
    block_pairs: int = Field(
        default=1 << 20,
        ge=1,
        description="association pairs gated per row block: bounds peak memory; smaller blocks are slower",
    )

    def model_post_init(self, context: object, /) -> None:
        if self.cosine_max <= self.cosine_min:
            raise ValueError(f"cosine_max ({self.cosine_max}) must exceed cosine_min ({self.cosine_min})")


__all__ += ["AssociationConfig", "AffinityConfig"]


class ParticleConfig(StrictModel):
    """Langevin particle sampler of a distribution over inlier sets (`matching.particles`).

    Dynamics, preconditioner, early stopping and rounding follow the reference's
    `LangevinMatcherParams`. The reference runs 1000 particles x 1000 iterations on a GPU; the
    defaults here are sized for a CPU (measurements: README, Why the defaults are what they are).
    """

    n_particles: int = Field(
        default=256,
        ge=1,
        description="Langevin particles per patch (reference 1000, sized for a GPU): more find the true set more "
        "often, at more matching time",
    )
    n_iterations: int = Field(
        default=100,
        ge=2,
        description="maximum Langevin steps (reference 1000), also the length of the noise annealing schedule: "
        "fewer lose registrations (why: matching/particles.py)",
    )
    max_associations: int | None = Field(
        default=128,
        ge=2,
        description="associations per patch given to the sampler, the best supported by the two-step walk count "
        "M'(M'1) (`support_pruning`); None = all. Cuts the cost per step ~(m / k)^2 and removes clutter",
    )
    start_scale: float = Field(
        default=1.0,
        gt=0,
        description="particles start uniform in [0, start_scale) per coordinate, with a rotation prior; the first "
        "step's squared gradient (~start_scale^2) sets how slowly the preconditioned step grows",
    )
    start_scale_free_rotation: float = Field(
        default=1.0,
        gt=0,
        description="start_scale without a rotation prior (2 helped on two worlds and not on two others: README, "
        "Why the defaults)",
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
    yaws: int = Field(
        default=72,
        ge=1,
        description="yaw grid of T_world_odom over [0, 2 pi); a step of d deg misplaces an older submap of the "
        "chain by up to sin(d / 2) of the path since",
    )
    classes: int = Field(
        default=1,
        ge=1,
        description="descriptor clusters rasterised as separate grids (1 = geometry only)",
    )
    orientation_bins: int = Field(
        default=16,
        ge=0,
        description="line samples go to one raster per orientation bin over [0, pi) (0 = points and lines "
        "share one raster; > 0: points have their own); cost grows with the rasters",
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
        default=0.95, ge=0, le=1, description="weight of the previous submaps' chain volume (0 = single submaps)"
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
        "search (`coarse`)",
    )
    exhaustive_max_patches: int = Field(
        default=100,
        ge=0,
        description="'auto' matches every patch of maps up to this many patches, and the coarse search's top "
        "k_coarse above it. Matching every patch costs about 7 ms per patch and submap on 2 cores until the fix",
    )
    k_global: int = Field(default=25, ge=1, description="K_global: patches per submap in 'global' mode (paper)")
    coarse_yaw_prior: bool = Field(
        default=True,
        description="'coarse' mode: match each candidate patch with the chain's yaw of T_world_odom at that "
        "patch as its rotation prior, instead of free rotation (false: free rotation)",
    )
    k_coarse: int = Field(
        default=100,
        ge=1,
        description="patches per submap in 'coarse' mode. The chain ranks the true patch low on a drive's "
        "first submaps: 100 fixed within a submap of matching every patch on three of four KITTI-map runs "
        "(5 submaps later on the fourth), with a third of the matching time; 25 fixed later (README: Why "
        "the defaults)",
    )
    global_fusion: Literal["auto", "always", "never"] = Field(
        default="auto",
        description="'coarse' mode: fuse the coarse search's patch ranking with the global descriptors' "
        "(reciprocal rank fusion). 'auto': only when the map's global descriptors come from a neural back end "
        "(anyloc, gem), as the classical ones rank the true patch at chance; 'always', 'never'",
    )
    fusion_rank_constant: float = Field(
        default=60.0,
        gt=0,
        description="k of the reciprocal rank fusion: a patch scores 1 / (k + rank) in each ranking (rank 1 = "
        "best), so a large k flattens the advantage of the first ranks (60: the usual choice, not tuned here)",
    )
    coarse: CoarseSearchConfig = Field(default_factory=CoarseSearchConfig)
    near_radius_m: float = Field(default=25.0, gt=0, description="disk radius around the predicted position, 'near' mode")
    near_patches: int = Field(default=2, ge=1, description="patches kept in 'near' mode (largest overlap first)")


__all__ += ["CoarseSearchConfig", "PlaceRecognitionConfig"]


class RegistrationConfig(StrictModel):
    """Weights and thresholds of `register_se2` (thresholds are the reference's `RegisterParams`)."""

    line_direction_weight: float = Field(
        default=25.0,
        ge=0,
        description="weight (m^2) of sin^2(line angle error) against a squared offset of 1 m; a line of "
        "length L scored by its endpoints weighs its direction by (L/2)^2 (reference: 1 m^2)",
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
    """Geometric verification of hypotheses (`matching.verification`, not in the paper): the
    heaviest clusters of a patch are re-ranked by the alignment of the posed ground primitives
    with the aerial ones beyond the patch's chance alignment (measurements: README, Why the
    defaults are what they are).
    """

    enabled: bool = Field(
        default=True, description="rank hypotheses by alignment beyond chance (false: particle mass only, the paper)"
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
    chance_yaws: int = Field(
        default=12, ge=1,
        description="the alignment a patch gives any pose by chance is the mean over this many evenly spaced yaws "
        "(x 5 positions); hypotheses are ranked by their alignment beyond it",
    )
    chance_offset_m: float = Field(
        default=10.0, ge=0,
        description="the chance poses put the submap's centre at the patch's centre and this far from it along the diagonals",
    )
    chunk_pairs: int = Field(
        default=8_000_000,
        ge=1,
        description="(pose, ground primitive, aerial primitive) triples evaluated at once by torch's ops on "
        "devices other than the CPU; bounds memory to about 10 bytes per triple (the CPU's compiled pass holds "
        "no such tensors)",
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
        default=16,
        ge=1,
        description="most patches matched together as one group (affinity, particles, registration, "
        "verification); P patches form ceil(P / patch_chunk) groups of equal size: bounds peak memory; on the CPU "
        "the groups run side by side on torch's threads; another value can round "
        "a patch's affinity entries an ulp apart (README, Reproducibility)",
    )
    verification: VerificationConfig = Field(default_factory=VerificationConfig)
    hypotheses_per_patch: int = Field(default=25, ge=1, description="L, clustered hypotheses kept per patch")
    cluster_translation_m: float = Field(default=1.0, gt=0, description="cluster radius in translation")
    cluster_rotation_deg: float = Field(default=5.0, gt=0, description="cluster radius in yaw")


__all__ += ["MatchConfig"]
