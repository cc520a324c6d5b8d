"""Reading and writing on-disk formats: sequence folders, pose files, orthophotos."""
