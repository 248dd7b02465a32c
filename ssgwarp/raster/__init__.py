"""The rasterizer op, ssgwarp.rasterization: settings, SH, torch reference, Warp ops; the scene.

Modules: launch, ops, rasterize, reference, rendering, scene, settings, sh."""
