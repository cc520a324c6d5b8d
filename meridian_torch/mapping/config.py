"""Validated settings of the segment → primitive conversion (paper / reference defaults).

Only pydantic is imported here so that configs stay cheap to load. Defaults follow the
reference implementation's `SegmentToPrimitiveConversionParams` with the paper-faithful
choices (alpha-shape outline, lines never made infinite).
"""

from __future__ import annotations

from pydantic import Field, model_validator

from meridian_torch.sim.config import StrictModel

__all__ = ["PrimitiveConfig"]


class PrimitiveConfig(StrictModel):
    """How segments become points and lines, and how outline edges fuse into coarse lines."""

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
    # 0.35 m (below the 0.5 m perpendicular merge tolerance) turns pixel stair-steps into long
    # edges: with the reference's 0 most line length sits in pieces under the matcher's 2 m
    # minimum (line recall of lines >= 2 m: 0.15 -> 0.93 on the default world, 0.06 -> 0.62 on kitti0).
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
