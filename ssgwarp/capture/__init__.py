"""Captures: COLMAP, LLFF and transforms.json folders read into a SceneData, lens undistortion, points.

Modules: datasets (SceneData, the layout detection, load_dataset / load_run), loaders (the layouts'
readers), lens, triangulate. The file formats they read are :mod:`ssgwarp.formats`'s."""
