"""The one categorical palette for group labels, shared by group-map renders and the viewer."""
from __future__ import annotations

import colorsys

import numpy as np
import torch

_BASE = np.array([
    [0.90, 0.10, 0.29], [0.24, 0.71, 0.29], [1.00, 0.88, 0.10], [0.00, 0.51, 0.78],
    [0.96, 0.51, 0.19], [0.57, 0.12, 0.71], [0.27, 0.94, 0.94], [0.94, 0.20, 0.90],
    [0.82, 0.96, 0.24], [0.98, 0.75, 0.83], [0.00, 0.50, 0.50], [0.86, 0.75, 1.00],
    [0.67, 0.43, 0.16], [1.00, 0.98, 0.78], [0.50, 0.00, 0.00], [0.67, 1.00, 0.76],
    [0.50, 0.50, 0.00], [1.00, 0.84, 0.71], [0.00, 0.00, 0.50], [0.50, 0.50, 0.50],
], dtype=np.float32)


def palette(k: int) -> np.ndarray:
    """``[k, 3]`` float32 RGB in [0, 1]; the first 20 are fixed, later ones golden-ratio hues."""
    if k <= len(_BASE):
        return _BASE[:k].copy()
    extra = []
    for i in range(k - len(_BASE)):
        h = (0.137 + i * 0.61803398875) % 1.0
        extra.append(colorsys.hsv_to_rgb(h, 0.65 + 0.3 * (i % 2), 0.85))
    return np.concatenate([_BASE, np.asarray(extra, dtype=np.float32)], axis=0)


def colorize_labels(labels: torch.Tensor | np.ndarray, k: int | None = None, ignore: int = -1) -> np.ndarray:
    """Colour an integer label map ``[..., ]`` → ``[..., 3]`` float32; ``ignore`` labels are black."""
    lab = labels.detach().cpu().numpy() if isinstance(labels, torch.Tensor) else np.asarray(labels)
    k = int(lab.max()) + 1 if k is None else k
    pal = palette(max(k, 1))
    out = np.zeros(lab.shape + (3,), dtype=np.float32)
    valid = (lab != ignore) & (lab >= 0) & (lab < len(pal))
    out[valid] = pal[lab[valid]]
    return out
