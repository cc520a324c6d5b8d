"""Validated configuration of the mapping stage: segment → primitive conversion, the aerial map
builder, ground observations, tracking and submaps.

Only pydantic is imported here so that configs stay cheap to load.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from meridian_torch.config.base import StrictModel

__all__ = ["PrimitiveConfig"]


class PrimitiveConfig(StrictModel):
    """How segments become points and lines, and how outline edges fuse into coarse lines.

    Defaults follow the reference implementation's `SegmentToPrimitiveConversionParams` with the
    paper-faithful choices (alpha-shape outline, lines never made infinite), except
    `outline_simplify_m` (reference 0).
    """

    # Outline (alpha shape)
    alpha: float = Field(
        default=1.0, gt=0, description="alpha shape: Delaunay triangles with circumradius < 1/alpha m are kept"
    )
    alpha_grid_m: float = Field(
        default=0.25, gt=0, description="cell of the grid the points are downsampled to before the alpha shape"
    )
    alpha_max_points: int | None = Field(
        default=None, ge=3, description="if set, the grid cell doubles until at most this many points remain"
    )
    alpha_ref_size_m: float | None = Field(
        default=None, gt=0, description="if set, alpha is scaled by min(1, ref / segment diameter)"
    )

    # Classification, in this order: area, compact point, thin line, circle point, outline lines
    min_area_m2: float = Field(default=1.0, ge=0, description="segments smaller than this are dropped")
    point_max_area_m2: float = Field(default=5.0, ge=0, description="a segment below this area ...")
    point_max_len_m: float = Field(
        default=5.0, ge=0, description="... and below this diameter becomes a point at its centre"
    )
    thin_line_max_minor_var_m2: float = Field(
        default=0.01, ge=0, description="a segment with minor PCA variance below this becomes one line; 0 = off"
    )
    line_min_length_m: float = Field(default=0.0, ge=0, description="emitted lines must be longer than this")
    circle_max_area_m2: float = Field(
        default=50.0, ge=0, description="circle test only below this area; the radius must be < sqrt(area / pi)"
    )
    circle_max_fit_error_frac: float = Field(
        default=0.3, gt=0, description="circle accepted if its RMS radial residual < this fraction of the radius"
    )
    outline_simplify_m: float = Field(
        default=0.35,
        ge=0,
        description="Douglas-Peucker tolerance (m) of the outline before its edges become lines; 0 = off (reference)",
    )
    border_margin_m: float = Field(
        default=0.5, ge=0, description="primitives must lie this far inside the border box (aerial sub-crops)"
    )

    # Line fusion into coarse lines
    line_merge_angle_deg: float = Field(default=10.0, gt=0, lt=90, description="maximum angle between fused lines")
    line_merge_short_m: float = Field(
        default=1.0, gt=0, description="below this length the angle limit grows as short / length, up to 45 deg"
    )
    line_merge_dist_m: float = Field(default=1.0, gt=0, description="maximum gap between fused lines")
    line_merge_perp_dist_m: float = Field(
        default=0.5, gt=0, description="maximum offset of one line's closest point from the other line"
    )
    line_merge_semantic_sim: float = Field(
        default=0.8, ge=-1, le=1, description="minimum descriptor cosine similarity of fused lines"
    )
    line_merge_max_sweeps: int = Field(default=1000, ge=1, description="cap on fusion sweeps")
    line_len_to_infinite: float | None = Field(
        default=None, gt=0, description="after fusion, longer lines become INFINITE (None = never; older ref. 15 m)"
    )

    @model_validator(mode="after")
    def _check_interactions(self) -> "PrimitiveConfig":
        if self.line_merge_perp_dist_m > self.line_merge_dist_m:
            raise ValueError("line_merge_perp_dist_m must be <= line_merge_dist_m")
        if self.point_max_area_m2 < self.min_area_m2:
            raise ValueError("point_max_area_m2 must be >= min_area_m2")
        return self


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
        description="workers describing patch batches (the same map): local processes (CPU only) or Ray actors; "
        "classical back ends scale with cores, each worker opens the orthophoto and holds its own back ends",
    )
    engine: Literal["local", "ray"] = Field(
        default="local",
        description="where batches are described: local processes, or Ray actors (extra 'distributed')",
    )
    ray_address: str | None = Field(
        default=None, description="engine ray: cluster to join (HEAD:6379); None starts a local one with `workers` CPUs"
    )


class CloudCleanupConfig(StrictModel):
    """Cleanup of each segment's points: voxel means, statistical outlier removal, then the
    largest DBSCAN cluster (per frame in 3D, and again in x-y after a submap is flattened)."""

    voxel_m: float = Field(default=0.1, gt=0, description="voxel downsampling, m")
    outlier_neighbours: int = Field(default=10, ge=1, description="statistical outlier removal: neighbours")
    outlier_std_ratio: float = Field(
        default=1.0, gt=0, description="statistical outlier removal: keep mean distance < mean + ratio * std"
    )
    dbscan_eps_m: float = Field(default=0.5, gt=0, description="DBSCAN radius, m; the largest cluster is kept")
    dbscan_min_points: int = Field(default=10, ge=1, description="DBSCAN core-point neighbourhood size")


class GroundObservationConfig(StrictModel):
    """Per-frame 3D observations: masks -> point clouds with occluded ("border") points (reference
    `SegmenterParams`; every default is the reference's except `pixel_stride`, `max_depth_m` and
    `occlusion_max_depth_m`)."""

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
        description="depth cutoff, m; farther pixels are ignored (paper 10 m, a RealSense-class range). Set it "
        "to your sensor's trustworthy range",
    )
    cleanup: CloudCleanupConfig = Field(
        default_factory=CloudCleanupConfig, description="cleanup of each mask's 3D points"
    )
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


class SubmapSpacingConfig(StrictModel):
    """Submap spacing once the robot is localized (replaces the three submap_* spacing keys from
    the fix on): after the fix a submap is matched cheaply near its predicted pose, so denser,
    overlapping submaps correct the online estimate more often (the authors' newer code: every
    20 m with a 40 m radius)."""

    trigger_path_m: float = Field(gt=0, description="trigger a submap after this much travel if any segment is new")
    min_interval_s: float = Field(ge=0, description="a submap this soon after the previous one is skipped")
    min_path_m: float = Field(ge=0, description="a submap after less travel than this is skipped")
    max_centre_lag_m: float | None = Field(
        default=None,
        gt=0,
        description="a submap's centre trails the robot by at most this much travel (None: no bound); where "
        "few segments are new, their median time lags and a postponed submap waited for it",
    )


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
        description="also trigger a submap after this much odometry travel (m) since the previous one if any "
        "segment is new (None: new-segment count only, as the paper)",
    )
    submap_min_interval_s: float = Field(
        default=5.0, ge=0, description="a submap this soon after the previous one is skipped (newer reference)"
    )
    submap_min_path_m: float = Field(
        default=20.0, ge=0, description="a submap after less odometry travel than this is skipped (newer reference)"
    )
    submap_spacing_after_fix: SubmapSpacingConfig | None = Field(
        default_factory=lambda: SubmapSpacingConfig(
            trigger_path_m=20.0, min_interval_s=0.0, min_path_m=20.0, max_centre_lag_m=20.0
        ),
        description="submap spacing from the localizer's global fix on (default: every 20 m, the authors' newer "
        "code; null: unchanged)",
    )
    occluded_ring_m: float = Field(
        default=0.5, ge=0, description="points in the outer ring (radius - this, radius] become occluded"
    )
    occluded_grid_m: float = Field(
        default=0.25, gt=0, description="occluded points sharing an x-y cell of this size with a real point are cleared"
    )
    flatten_cleanup: CloudCleanupConfig = Field(
        default_factory=lambda: CloudCleanupConfig(dbscan_eps_m=0.25),
        description="cleanup of each segment's x-y points after the submap is flattened along odom z",
    )
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
    mapping_rate_hz: float | None = Field(
        default=6.0,
        gt=0,
        description="[paper] frames are mapped at this rate at most: the first frame of each 1/rate interval of a "
        "clock started at the first frame; the others only carry odometry to the localizer (None: every frame)",
    )
    frame_descriptor_dist_m: float = Field(
        default=5.0, gt=0, description="travel between frame global descriptors (submap descriptor stack)"
    )
    batch_size: int = Field(default=8, ge=1, description="frames segmented together by map_ground")
    perception_threads: int = Field(
        default=2, ge=1, description="batches perceived side by side while the tracker integrates an earlier one "
        "(each holds its batch's images, masks and features in memory)",
    )
    max_odometry_gap_s: float = Field(
        default=1.0, gt=0, description="frames whose odometry would be interpolated across a longer gap between "
        "poses are refused before the run (a 10 s gap over a turn was bridged 6 m / 65 deg off)",
    )


__all__ += ["AerialMapConfig", "CloudCleanupConfig", "GroundObservationConfig", "GroundTrackingConfig", "GroundMapConfig"]
