"""Geometry shared by all stages: SE(3), trajectories and planar poses / angles (numpy float64,
`se3`, `trajectory`, `planar`), SE(2) and line angles (batched torch, `se2`), points against
segments (`segments`)."""
