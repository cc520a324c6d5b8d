"""Validated configuration: one pydantic model per stage, composed in `MeridianConfig`.

Config files are YAML. A file may start from another with `extends: other.yaml` (resolved
relative to the file) and then overrides any subset of keys. Values of keys ending in `path`
that start with `./` or `../` are resolved relative to the file that sets them. Unknown keys and bad values are
`ConfigError`s that name the file and the dotted key. `overrides` are `a.b.c=value` strings
whose value is parsed as YAML.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError, model_validator

from meridian_torch.core.paths import shipped_dir
from meridian_torch.errors import ConfigError
from meridian_torch.mapping.config import PrimitiveConfig
from meridian_torch.matching.config import ClipperConfig, MatchConfig
from meridian_torch.perception.config import (
    DescriptorConfig,
    GlobalDescriptorConfig,
    OnnxGraphsConfig,
    SegmenterConfig,
)
from meridian_torch.sim.config import SimConfig, StrictModel

__all__ = [
    "RuntimeConfig",
    "PerceptionConfig",
    "AerialMapConfig",
    "GroundObservationConfig",
    "GroundTrackingConfig",
    "GroundMapConfig",
    "BackendConfig",
    "EvaluationConfig",
    "MeridianConfig",
    "CONFIG_DIR",
    "load_config",
    "dump_config",
    "config_key",
]

CONFIG_DIR = shipped_dir("configs")  # the checkout's configs/, or a wheel's bundled copy


class RuntimeConfig(StrictModel):
    """Device and dtype are chosen once here and read from the tensors everywhere else."""

    device: str = Field(default="cpu", pattern=r"^(cpu|auto|cuda(:\d+)?)$")
    dtype: Literal["float32", "float64"] = "float32"
    num_threads: int = Field(default=0, ge=0, description="torch CPU threads; 0 = torch's default")


class PerceptionConfig(StrictModel):
    """Back ends of segmentation and description; aerial and ground share the describers so
    that their descriptors are comparable."""

    aerial_segmenter: SegmenterConfig = SegmenterConfig()
    ground_segmenter: SegmenterConfig = SegmenterConfig()
    descriptor: DescriptorConfig = DescriptorConfig()
    global_descriptor: GlobalDescriptorConfig = GlobalDescriptorConfig()
    ground_engine: Literal["torch", "onnx"] = Field(
        default="torch",
        description="onnx: the ground pipeline's segmenter and describers run exported graphs with onnxruntime only",
    )
    onnx: OnnxGraphsConfig = OnnxGraphsConfig()


class AerialMapConfig(StrictModel):
    patch_size_m: float = Field(default=60.0, gt=0)
    patch_overlap: float = Field(default=0.5, ge=0, lt=1, description="50 % overlap = 30 m stride")
    segmentation_crop_m: float | None = Field(
        default=None, gt=0, description="segment each patch in square sub-crops of this size (None: whole patch)"
    )
    batch_size: int = Field(default=4, ge=1, description="patches segmented together")
    workers: int = Field(
        default=1,
        ge=1,
        description="worker processes describing patch batches (CPU only; same map). Classical back ends: set "
        "it to the number of cores (2 on 2 cores: 1.55x faster for a 600 m x 600 m map, 1.23x for 300 m; "
        "scripts/bench_aerial.py). Each worker holds its own copy of the orthophoto and the back ends",
    )


class GroundObservationConfig(StrictModel):
    """Per-frame 3D observations: masks -> point clouds with occluded ("border") points (reference
    `SegmenterParams`; every default is the reference's)."""

    erosion_px: int = Field(default=3, ge=0, description="elliptical mask erosion radius, pixels (kernel 2r+1)")
    pixel_stride: int | None = Field(
        default=None,
        ge=1,
        description="back-project every n-th pixel in both axes; None: the reference's 4 scaled to the image "
        "width and rounded down (4 at 1280 px, 2 at 640 px, 1 at 480 px)",
    )
    max_depth_m: float = Field(
        default=15.0,
        gt=0,
        description="depth cutoff; farther pixels are ignored (paper 10 m, a RealSense-class range). 15 m: within "
        "10 m a road-following camera sees almost only the road and its borders; on the demo world 15 m gave "
        "2-9 points and 70-190 lines per submap instead of 0-2 and 30-80, and true-patch registration rose from "
        "41 to 58 % (known rotation, top-25) and 23 to 33 % (unknown). Set it to your sensor's trustworthy range",
    )
    voxel_m: float = Field(default=0.1, gt=0, description="voxel downsampling of each observation")
    outlier_neighbours: int = Field(default=10, ge=1, description="statistical outlier removal: neighbours")
    outlier_std_ratio: float = Field(
        default=1.0, gt=0, description="statistical outlier removal: keep mean distance < mean + ratio * std"
    )
    dbscan_eps_m: float = Field(default=0.5, gt=0, description="DBSCAN radius; the largest cluster is kept")
    dbscan_min_points: int = Field(default=10, ge=1, description="DBSCAN core-point neighbourhood size")
    min_mask_pixels: int = Field(default=0, ge=0, description="masks with fewer pixels are ignored")
    occlusion_edge_frac: float = Field(
        default=0.02, ge=0, le=0.5, description="image-edge band width, fraction of the larger image side"
    )
    occlusion_edge_max_frac: float = Field(
        default=0.15, ge=0, le=0.5, description="cap of the band measured from the image border, same unit"
    )
    occlusion_max_depth_m: float = Field(
        default=14.0, gt=0, description="points deeper than this (up to max_depth_m) are occluded (depth-cutoff band; "
        "paper 9 m with its 10 m cutoff)"
    )
    occluded_clearance_m: float = Field(
        default=0.1, ge=0, description="real points closer than this to an occluded point are deleted"
    )

    @model_validator(mode="after")
    def _check_depths(self) -> "GroundObservationConfig":
        if self.occlusion_max_depth_m > self.max_depth_m:
            raise ValueError("occlusion_max_depth_m must be <= max_depth_m")
        return self


class GroundTrackingConfig(StrictModel):
    """Association, life cycle and merging of 3D segments (reference `SegmentMappingParams`)."""

    iom_voxel_m: float = Field(default=0.25, gt=0, description="[paper] voxel of the overlap (IoM) test")
    min_iom: float = Field(default=0.2, ge=0, le=1, description="[paper] minimum intersection over minimum")
    min_cosine: float = Field(default=0.8, ge=-1, lt=1, description="[paper] minimum descriptor cosine")
    segment_voxel_m: float = Field(default=0.1, gt=0, description="voxel of the accumulated segment clouds")
    min_sightings: int = Field(default=2, ge=1, description="nursery segments seen this often become active")
    max_unseen_s: float = Field(
        default=0.4, ge=0, description="unseen longer than this: nursery deleted, active -> inactive"
    )
    retire_after_s: float = Field(default=15.0, ge=0, description="inactive segments unseen this long retire")
    retire_distance_m: float = Field(
        default=10.0, ge=0, description="inactive segments retire when the camera is this far from their last sighting"
    )
    cleanup_dbscan_eps_m: float = Field(default=1.0, gt=0, description="DBSCAN radius of the final cleanup")
    cleanup_dbscan_min_points: int = Field(default=10, ge=1, description="DBSCAN core size of the final cleanup")
    min_max_extent_m: float = Field(
        default=0.25, ge=0, description="inactive segments whose largest PCA extent is below this are dropped"
    )
    unocclude_dist_m: float = Field(
        default=0.1, ge=0, description="occluded voxels with a real point this close to their centre are cleared"
    )
    max_merge_passes: int = Field(default=100, ge=0, description="merging passes per frame")


class GroundMapConfig(StrictModel):
    """Ground mapping: per-frame observations, 3D segment tracking, and 2D submaps (paper III-A)."""

    observation: GroundObservationConfig = GroundObservationConfig()
    tracking: GroundTrackingConfig = GroundTrackingConfig()
    submap_trigger_new_segments: int = Field(default=20, ge=1)
    submap_max_segments: int = Field(default=120, ge=1)
    submap_radius_m: float = Field(default=40.0, gt=0)
    submap_trigger_path_m: float | None = Field(
        default=40.0,
        gt=0,
        description="also trigger after this much odometry travel since the previous submap if any segment is "
        "new (None: new-segment count only, as the paper); keeps submaps coming with segmenters that yield "
        "few segments per frame (classical back end: ~1 submap per 300 m with the count alone)",
    )
    submap_min_interval_s: float = Field(
        default=5.0, ge=0, description="a submap this soon after the previous one is skipped (newer reference)"
    )
    submap_min_path_m: float = Field(
        default=20.0, ge=0, description="a submap after less odometry travel than this is skipped (newer reference)"
    )
    occluded_ring_m: float = Field(
        default=0.5, ge=0, description="points in the outer ring (radius - this, radius] become occluded"
    )
    occluded_grid_m: float = Field(
        default=0.25, gt=0, description="occluded points sharing an x-y cell of this size with a real point are cleared"
    )
    flatten_voxel_m: float = Field(default=0.1, gt=0, description="2D cleanup after flattening: voxel")
    flatten_outlier_neighbours: int = Field(default=10, ge=1, description="2D cleanup: statistical outlier neighbours")
    flatten_outlier_std_ratio: float = Field(default=1.0, gt=0, description="2D cleanup: statistical outlier ratio")
    flatten_dbscan_eps_m: float = Field(default=0.25, gt=0, description="2D cleanup: DBSCAN radius (largest cluster)")
    flatten_dbscan_min_points: int = Field(default=10, ge=1, description="2D cleanup: DBSCAN core size")
    point_min_height_m: float = Field(
        default=0.3, ge=0, description="segments flatter than this (odom z extent) give no point primitive; 0 = reference"
    )
    artifact_line_samples: int = Field(
        default=10, ge=2, description="samples along a line for the FOV / depth-cutoff artefact test"
    )
    artifact_min_near_fraction: float = Field(
        default=0.1, ge=0, le=1, description="lines need this fraction of samples near their segment's points"
    )
    artifact_min_clear_fraction: float = Field(
        default=0.1, ge=0, le=1, description="lines need this fraction of samples away from every occluded point"
    )
    artifact_dist_m: float = Field(default=0.5, gt=0, description="distance used by both artefact tests")
    frame_descriptor_dist_m: float = Field(
        default=5.0, gt=0, description="travel between frame global descriptors (submap descriptor stack)"
    )
    batch_size: int = Field(default=8, ge=1, description="frames segmented together by map_ground")
    max_odometry_gap_s: float = Field(
        default=1.0, gt=0, description="frames whose odometry would be interpolated across a longer gap between "
        "poses are refused before the run (a 10 s gap over a turn was bridged 6 m / 65 deg off)",
    )


class BackendConfig(StrictModel):
    """Robust pose graph and incremental localizer (fact sheet sections 5.2-5.7).

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
        default=True, description="affinity = cbrt(s * q_i * q_j) with q = probability / best of its (submap, patch)"
    )
    affinity_eps: float = Field(default=1e-4, ge=0, description="affinities at or below this are dropped")
    max_clipper_candidates: int = Field(
        default=4000,
        ge=2,
        description="CLIPPER problems (candidates left after pruning those that cannot join the densest "
        "clique) larger than this are solved in even chunks, then once more on the pooled chunk inliers "
        "(reference 100000 before pruning; a dense float64 4000^2 matrix is 128 MB)",
    )
    clipper: ClipperConfig = Field(
        default_factory=lambda: ClipperConfig(rounding="support"),
        description="CLIPPER on the loop-closure graph; 'support' rounding keeps every mutually consistent "
        "candidate of the converged solution (the reference's round(F) drops members of weighted cliques)",
    )
    odom_trans_sigma_m: float = Field(default=0.05, gt=0, description="odometry between-factor sigma per frame step (reference)")
    odom_rot_sigma_deg: float = Field(default=0.05, gt=0, description="odometry between-factor yaw sigma per frame step (reference)")
    prior_trans_sigma_m: float = Field(default=2.0, gt=0, description="loop-closure prior sigma x, y (reference)")
    prior_rot_sigma_deg: float = Field(default=5.0, gt=0, description="loop-closure prior yaw sigma (reference)")
    attempt_min_inliers: int = Field(
        default=3,
        ge=1,
        description="gate 1: pre-fix inliers needed before a fix attempt (re-match of all submaps); reference 1. "
        "An attempt re-matches near the rough trajectory of these inliers, so it tends to confirm them: on the "
        "KITTI 00 world (300 frames, top-25 place recognition) two chance-consistent candidates seeded attempts "
        "until one committed a wrong fix (online ATE 464 m) with 1; with 3 no attempt ran. The demo world "
        "had 5 pre-fix inliers by its first possible attempt, so its fix is unchanged",
    )
    fix_min_inliers: int = Field(default=6, ge=1, description="[paper] global fix: >= 6 inlier loop closures")
    fix_min_inlier_fraction: float = Field(
        default=0.5, gt=0, le=1, description="[paper] ... and inliers >= this fraction of the submaps so far"
    )
    commit_accepted_inliers: bool = Field(
        default=True, description="after the fix, drop the alternatives of submaps that have an inlier"
    )
    commit_delay_submaps: int = Field(
        default=2, ge=0, description="the most recent submaps keep their alternatives (reference delay)"
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


class EvaluationConfig(StrictModel):
    success_translation_m: float = Field(default=5.0, gt=0, description="[paper] registration success < 5 m")
    success_rotation_deg: float = Field(default=5.0, gt=0, description="[paper] ... and < 5 deg")
    success_rotation_deg_loose: float = Field(default=10.0, gt=0, description="reference default, also reported")
    success_top_k: list[int] = Field(default=[1, 5, 10, 25], min_length=1, description="[paper] top-L success rates")
    max_time_difference_s: float = Field(
        default=0.01, ge=0, description="an estimate and a ground-truth pose pair up within this time (evo's default)"
    )


class MeridianConfig(StrictModel):
    runtime: RuntimeConfig = RuntimeConfig()
    sim: SimConfig = SimConfig()
    perception: PerceptionConfig = PerceptionConfig()
    primitives: PrimitiveConfig = PrimitiveConfig()
    aerial_map: AerialMapConfig = AerialMapConfig()
    ground_map: GroundMapConfig = GroundMapConfig()
    matching: MatchConfig = MatchConfig()
    backend: BackendConfig = BackendConfig()
    evaluation: EvaluationConfig = EvaluationConfig()


def _read_yaml(path: Path, chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    if path in chain:
        raise ConfigError(f"{path}: circular 'extends' chain")
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    _resolve_relative_paths(data, path.parent)
    base = data.pop("extends", None)
    if base is None:
        return data
    return _deep_merge(_read_yaml((path.parent / str(base)).resolve(), chain + (path,)), data)


def _resolve_relative_paths(node: dict[str, Any], folder: Path) -> None:
    for key, value in node.items():
        if isinstance(value, dict):
            _resolve_relative_paths(value, folder)
        elif str(key).endswith("path") and isinstance(value, str) and value.startswith(("./", "../")):
            node[key] = str((folder / value).resolve())


def _deep_merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _apply_override(data: dict[str, Any], override: str) -> None:
    key, sep, raw = override.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"override {override!r}: expected KEY=VALUE, e.g. sim.seed=3")
    parts = key.strip().split(".")
    node = data
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {override!r}: {part!r} is not a section")
        node = child
    try:
        node[parts[-1]] = yaml.safe_load(raw)
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {override!r}: value is not valid YAML: {exc}") from None


def _format_validation_error(source: str, exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        key = ".".join(str(p) for p in err["loc"]) or "(top level)"
        if err["type"] == "extra_forbidden":
            lines.append(f"{source}: unknown key '{key}'")
        else:
            lines.append(f"{source}: {key}: {err['msg']} (got {err.get('input')!r})")
    return "\n".join(lines)


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> MeridianConfig:
    """Load and validate a config file (default: configs/default.yaml) with KEY=VALUE overrides."""
    path = Path(path) if path is not None else CONFIG_DIR / "default.yaml"
    data = _read_yaml(path.resolve())
    for override in overrides:
        _apply_override(data, override)
    source = str(path) + (" with overrides" if overrides else "")
    try:
        return MeridianConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(source, exc)) from None


def dump_config(config: MeridianConfig) -> str:
    """The fully resolved config as YAML (every key, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)


def config_key(*parts: Any) -> str:
    """A short hash of JSON-able config parts (and the package version): names cached products."""
    import hashlib
    import json

    from meridian_torch import __version__

    return hashlib.sha256(json.dumps([__version__, *parts], sort_keys=True).encode()).hexdigest()[:12]
