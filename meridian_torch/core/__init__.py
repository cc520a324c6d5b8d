"""Foundations every layer may import: nothing here imports another meridian_torch package."""
