"""Metrics, evaluation, renders and camera paths (ssgwarp evaluate, ssgwarp render).

Modules: evaluate, metrics, render, style_distance, table."""
