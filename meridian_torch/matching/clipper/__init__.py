"""Batched CLIPPER: the densest consistent set of associations in a weighted consistency graph.

`solve_clipper` re-implements the projected-gradient / penalty-homotopy solver of CLIPPER
(Lusk et al., v0.2.4) over a batch of dense, padded problems, plus three roundings of the
continuous solution to a set of inliers. Every returned set is a clique of the constraint
graph. Only torch is needed for the solve; the exact "densest" rounding imports scipy lazily.

Modules: `dense` (`solve_clipper` and its input checks), `sparse` (`solve_clipper_sparse` on
sparse edges), `ascent` (the continuous solve both share: penalty homotopy around projected
gradient ascent), `kernels` (that solve compiled, for one sparse CPU problem), `rounding`
(continuous solution to a clique), `result` (`ClipperResult`).
Names with a leading underscore are internal to the package.
"""

from meridian_torch.matching.clipper.dense import solve_clipper
from meridian_torch.matching.clipper.result import ClipperResult, inlier_indices
from meridian_torch.matching.clipper.sparse import solve_clipper_sparse

__all__ = ["ClipperResult", "inlier_indices", "solve_clipper", "solve_clipper_sparse"]
