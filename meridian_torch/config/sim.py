"""Validated configuration of the simulator (the `sim:` block of a config file)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from meridian_torch.config.base import StrictModel

__all__ = [
    "WorldConfig",
    "ClassRasterConfig",
    "SunConfig",
    "OrthoRenderConfig",
    "CameraConfig",
    "GroundRenderConfig",
    "TrajectoryConfig",
    "OdometryConfig",
    "SimConfig",
]


class ClassRasterConfig(StrictModel):
    """A world built from a semantic class raster instead of procedurally.

    `path` is either one label image (pixel value = class id) or a folder of binary masks
    `classK.png` (0 = inside, as in the cross_view_slam maps). `classes` maps the raster's
    ids (K) to simulator class names; unmapped pixels become `fill_class`.
    """

    path: str
    meters_per_pixel: float = Field(gt=0)
    classes: dict[int, str]
    fill_class: str = "grass"
    flip_vertical: bool = False  # rasters stored y-up (row 0 = south) need a flip
    object_spacing_m: float = Field(default=6.0, gt=0, description="mean spacing of trees/cars synthesized in class areas")


class WorldConfig(StrictModel):
    kind: Literal["procedural", "class_raster"] = "procedural"
    size_m: tuple[float, float] = Field(default=(400.0, 400.0), description="east x north extent, procedural worlds")
    resolution_m: float = Field(default=0.2, gt=0, le=1.0, description="cell size of the world rasters")
    urban_fraction: float = Field(default=0.5, ge=0, le=1)
    road_spacing_m: float = Field(default=90.0, gt=10)
    road_width_m: float = Field(default=8.0, gt=2)
    buildings_per_ha: float = Field(default=6.0, ge=0, description="in urban areas")
    trees_per_ha: float = Field(default=25.0, ge=0, description="in natural areas")
    bushes_per_ha: float = Field(default=20.0, ge=0)
    rocks_per_ha: float = Field(default=6.0, ge=0)
    cars_per_ha: float = Field(default=8.0, ge=0, description="on parking lots and road sides, urban areas")
    fences: int = Field(default=6, ge=0)
    water_fraction: float = Field(default=0.04, ge=0, le=0.5)
    soil_fraction: float = Field(default=0.10, ge=0, le=0.5)
    class_raster: ClassRasterConfig | None = None

    @model_validator(mode="after")
    def _raster_given(self) -> "WorldConfig":
        if self.kind == "class_raster" and self.class_raster is None:
            raise ValueError("kind 'class_raster' needs the class_raster block")
        return self


class SunConfig(StrictModel):
    """Where the sun stands; the orthophoto and the ground frames of one world share it."""

    sun_azimuth_deg: float = Field(default=135.0, description="direction the sun shines from, clockwise from north")
    sun_elevation_deg: float = Field(default=45.0, gt=0, le=90)


class OrthoRenderConfig(SunConfig):
    meters_per_pixel: float = Field(default=0.3, gt=0)
    shadows: bool = True
    texture_strength: float = Field(default=1.0, ge=0)
    outdated: bool = Field(default=False, description="seasonal colour change and some objects removed or added")
    outdated_change_fraction: float = Field(default=0.15, ge=0, le=1)


class CameraConfig(StrictModel):
    width: int = Field(default=640, ge=16)
    height: int = Field(default=360, ge=16)
    hfov_deg: float = Field(default=90.0, gt=10, lt=170)
    mount_xyz: tuple[float, float, float] = Field(default=(0.3, 0.0, 1.2), description="camera position in base frame")
    mount_rpy_deg: tuple[float, float, float] = Field(default=(0.0, 5.0, 0.0), description="roll, pitch down (+), yaw")
    depth_scale: float = Field(default=1000.0, gt=0)


class GroundRenderConfig(SunConfig):
    max_depth_m: float = Field(default=20.0, gt=0, description="sensor range; farther pixels get no depth")
    render_distance_m: float = Field(default=120.0, gt=0, description="farther geometry is sky in RGB")
    depth_noise_a: float = Field(default=0.002, ge=0, description="depth noise std = a * z^2 + b")
    depth_noise_b: float = Field(default=0.005, ge=0)
    rgb_noise_std: float = Field(default=2.0, ge=0, description="pixel noise in 8-bit units")
    batch_size: int = Field(default=8, ge=1)
    ambient: float = Field(default=0.45, ge=0, le=1, description="unlit fraction of the light")
    haze_strength: float = Field(default=0.35, ge=0, le=1, description="blend towards the horizon colour at render distance")
    samples_per_ray: int = Field(default=640, ge=16, description="height samples per image column, geometric in distance")
    min_distance_m: float = Field(default=0.2, gt=0, description="nearest geometry a ray can hit")
    column_oversample: float = Field(default=1.5, ge=0.5, description="ray columns per image column")
    row_oversample: float = Field(default=1.25, ge=0.5, description="hit-table rows per image row")


class TrajectoryConfig(StrictModel):
    kind: Literal["drive", "file"] = "drive"
    length_m: float = Field(default=1000.0, gt=0)
    speed_mps: float = Field(default=5.0, gt=0)
    frame_rate_hz: float = Field(default=3.0, gt=0)
    odometry_rate_hz: float = Field(default=20.0, gt=0)
    path: str | None = Field(default=None, description="TUM or KITTI file, kind 'file'")
    format: Literal["tum", "kitti"] = "tum"
    kitti_times_path: str | None = None
    alignment_path: str | None = Field(default=None, description="kitti_gt_alignment.json-style similarity into the class raster")
    alignment_map: str | None = None
    alignment_y_up: bool = Field(default=True, description="alignment rows count from the raster's south edge (stored y-up)")
    max_frames: int | None = Field(default=None, ge=1)

    @model_validator(mode="after")
    def _file_given(self) -> "TrajectoryConfig":
        if self.kind == "file" and not self.path:
            raise ValueError("kind 'file' needs path")
        return self


class OdometryConfig(StrictModel):
    kind: Literal["perfect", "drift", "file"] = "drift"
    translation_drift: float = Field(default=0.01, ge=0, description="std of relative translation error per metre")
    scale_drift: float = Field(default=0.005, ge=0, description="std of a constant scale error")
    yaw_drift_deg_per_sqrt_m: float = Field(default=0.05, ge=0, description="yaw random-walk std per sqrt(m)")
    path: str | None = Field(default=None, description="odometry estimate file (TUM or KITTI), kind 'file'")
    format: Literal["tum", "kitti"] = "kitti"

    @model_validator(mode="after")
    def _file_given(self) -> "OdometryConfig":
        if self.kind == "file" and not self.path:
            raise ValueError("kind 'file' needs path")
        return self


class SimConfig(StrictModel):
    name: str = "default-world"
    seed: int = 0
    world: WorldConfig = WorldConfig()
    ortho: OrthoRenderConfig = OrthoRenderConfig()
    camera: CameraConfig = CameraConfig()
    render: GroundRenderConfig = GroundRenderConfig()
    trajectory: TrajectoryConfig = TrajectoryConfig()
    odometry: OdometryConfig = OdometryConfig()

    @model_validator(mode="after")
    def _alignment_matches_raster(self) -> "SimConfig":
        raster = self.world.class_raster
        if raster is not None and self.trajectory.alignment_path and self.trajectory.alignment_y_up != raster.flip_vertical:
            raise ValueError("trajectory.alignment_y_up must equal world.class_raster.flip_vertical "
                             "(the alignment is expressed in the stored raster's rows)")
        return self
