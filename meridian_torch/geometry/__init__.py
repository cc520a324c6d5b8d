"""Rigid-body geometry shared by all stages (numpy, float64)."""
