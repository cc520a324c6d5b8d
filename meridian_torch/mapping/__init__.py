"""Aerial map building, ground segment mapping and submaps, and segment → primitive conversion."""
