"""Captures and file formats: COLMAP, LLFF, transforms.json, lens undistortion, PLY.

Modules: colmap, datasets, formats, lens, ply."""
