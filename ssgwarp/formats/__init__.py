"""File formats, one home: splat files (read and written), other tools' output layouts, COLMAP models.

Modules: registry (the formats by name: one detection, one reader and one writer dispatch), ply,
compressed_ply, splat, spz, sog, gltf, ksplat (read only), codec (what the codecs share), layouts
(graphdeco / gsplat / nerfstudio outputs), colmap (COLMAP model files)."""
