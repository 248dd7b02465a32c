"""Metrics, evaluation, renders and camera paths (ssgwarp evaluate, ssgwarp render, ssgwarp export), and what
measures images for the stages too: the feature extractors and their losses, LPIPS and RAFT.

Modules: evaluate, export, features, metrics, networks, render, style_distance, table."""
