"""Segment → primitive conversion: outlines, point/line classification and line fusion.

`conversion.segments_to_primitives` is the entry point; `outline` holds the alpha-shape outline
and its simplified edges (triangulated and walked by `outline_kernels`, compiled), `line_fusion` the
merging of fine lines into coarse ones.

A segment is a 2D point set in metres (aerial: world centres of its mask pixels; ground:
flattened 3D points) with one semantic descriptor. Following the paper (section III-A) and the
reference implementation, each segment is classified in this order:

1. outline: alpha shape of the points on a 0.25 m grid (Delaunay triangles with circumradius
   < 1/alpha, boundary edges polygonized and unioned); a result other than one polygon means
   no outline;
2. area below `min_area_m2`: dropped;
3. compact (small area and diameter): one point at the centre (mean of the points);
4. thin (minor PCA variance below a threshold): one line between the extreme projections;
5. roughly circular and small: one point at the fitted circle centre;
6. otherwise every outline edge becomes a line (after Douglas-Peucker simplification of the
   outline by `outline_simplify_m`, if set).
Primitives outside the border box (shrunk by `border_margin_m`) are not emitted; a point whose
centre is outside drops its whole segment. All lines are then fused into coarse lines.

Departures from the reference, all deliberate:
- grid downsampling keeps the mean of each cell of one global lattice (reference: the first
  point found), so the result does not depend on point order;
- only the grid points within 3 cells of an empty cell enter the Delaunay triangulation (see
  `outline.BAND_CELLS`): the union of the polygonized faces fills every hole, so deeper points do
  not change the outline; they only cost time (a 2000 m^2 segment has ~32 000 grid points,
  ~2 000 in the band);
- the thin-line rule needs only the raw points, so it also applies when the alpha shape fails
  (collinear grid points, several polygons), where the reference drops the segment: an
  axis-aligned bar one grid cell wide would otherwise vanish or not depending on grid alignment;
- the short-line angle relaxation is angle * short / length (reference: angle / length, equal at
  the 1 m default), and angles are compared as angles (reference: |sin| against radians);
- line fusion is a deterministic sequence of sweeps; see `line_fusion.fuse_lines`;
- `outline_simplify_m` (default 0.35 m; 0 = reference) simplifies the outline by Douglas-Peucker
  before its edges become lines, each run of edges inside the border box separately (see
  `outline.simplified_outline_edges`). Below the 0.5 m perpendicular merge offset, it turns the
  pixel stair-steps of straight sides into long edges; unsimplified, most line length sits in
  pieces shorter than the matcher's 2 m `min_line_length_m` (recall figures in the README, "Why
  the defaults are what they are"). The cost: it can bend a short end piece of a side past the
  10 deg fusion angle, so that side splits (the xfail in tests/test_segment_to_primitives.py).
"""
