"""Geometry shared by all stages: SE(3) and trajectories (numpy float64), SE(2) (batched torch)."""
