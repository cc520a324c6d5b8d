"""Back end: loop-closure candidates, their consistency graph, the GTSAM pose graph and the localizer."""
