"""meridian-torch: cross-view geo-localization of ground robots in aerial orthophotos.

Importing the package is cheap and has no side effects: heavy optional libraries (gtsam,
onnx, onnxruntime, matplotlib, rasterio) are imported only inside the functions that use them.
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"
__all__ = ["__version__"]

logging.getLogger(__name__).addHandler(logging.NullHandler())
