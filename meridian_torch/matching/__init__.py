"""Cross-view matching: associations, inlier-set sampling and SE(2) registration of association sets."""
