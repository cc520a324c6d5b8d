"""Choosing the aerial patches a ground submap is matched against.

`descriptors`: the paper's global-descriptor ranking, exhaustive and 'near' selection;
`coarse`: the weight-free coarse global search over the whole map from the primitives.
"""

from meridian_torch.matching.place_recognition.coarse import (
    CoarseMap,
    CoarsePriors,
    CoarseSearch,
    build_coarse_map,
    chain_scores,
    patch_priors,
    submap_scores,
)
from meridian_torch.matching.place_recognition.descriptors import (
    disk_overlap,
    resolved_mode,
    select_patches,
    stack_similarity,
)

__all__ = [
    "CoarseMap",
    "CoarsePriors",
    "CoarseSearch",
    "build_coarse_map",
    "chain_scores",
    "disk_overlap",
    "patch_priors",
    "resolved_mode",
    "select_patches",
    "stack_similarity",
    "submap_scores",
]
