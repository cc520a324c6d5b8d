"""Perception: image segmentation, per-segment semantic descriptors and global (place) descriptors.

Every back end implements the protocols in `protocols.py` over batched tensors, so the classical,
weight-free back ends (`classical/`) and the neural ones in `neural/` (SAM/FastSAM, DINOv2 mask pooling,
AnyLoc) are interchangeable. Back ends are built from the configs in `meridian_torch.config.perception` through
the factories in `factory.py`. Importing this package is cheap: the heavy libraries (OpenCV,
scikit-image) are imported by the modules that need them.
"""

from __future__ import annotations

__all__: list[str] = []
