"""Torch-only helpers every layer uses: geometry, cameras, atomic files, images, colours.

Modules: cameras, fileio, geometry, imaging, optim, palette."""
