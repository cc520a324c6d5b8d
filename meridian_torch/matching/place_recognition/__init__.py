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
    NEURAL_GLOBAL_BACKENDS,
    disk_overlap,
    fuses_global,
    rank_fusion,
    reads_global_descriptors,
    resolved_mode,
    select_patches,
    stack_similarity,
)

__all__ = [
    "NEURAL_GLOBAL_BACKENDS",
    "CoarseMap",
    "CoarsePriors",
    "CoarseSearch",
    "build_coarse_map",
    "chain_scores",
    "disk_overlap",
    "fuses_global",
    "patch_priors",
    "rank_fusion",
    "reads_global_descriptors",
    "resolved_mode",
    "select_patches",
    "stack_similarity",
    "submap_scores",
]
