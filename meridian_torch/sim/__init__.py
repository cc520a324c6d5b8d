"""Simulator: procedural and raster-based worlds, orthophoto and RGB-D renderers, drives, odometry."""
