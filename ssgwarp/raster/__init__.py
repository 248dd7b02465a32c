"""The rasterizer op, ssgwarp.rasterization: settings, SH, torch reference, Warp ops; the scene and its groups.

Modules: blend_ops, cpu_threads, groups, launch, ops, private_api (every use of Warp's and torch's private APIs),
rasterize, reference, rendering, scene, settings, sh, sh_ops, ssim_ops."""
