"""Neural perception back ends (DINOv2, AnyLoc, SAM, FastSAM). Weights load from local files only."""
