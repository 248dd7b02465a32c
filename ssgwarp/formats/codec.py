"""What the splat codecs share: numpy views of a scene and back, the 8-bit and n-bit quantisers,
the "smallest three" index table, atomic writes and the Morton order."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..core.fileio import atomic_path
from ..raster.scene import GaussianScene

OTHER_COMPONENTS = np.array([[j for j in range(4) if j != i] for i in range(4)])   # row i: the indices other than i

def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))


def logit(p: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """The inverse of :func:`sigmoid`, ``p`` kept ``eps`` off 0 and 1 (8-bit alphas of 0 and 255)."""
    p = np.clip(np.asarray(p, np.float64), eps, 1.0 - eps)
    return np.log(p / (1.0 - p))


def to_u8(x: np.ndarray) -> np.ndarray:
    """Round half away from zero (as C's ``round`` on these non-negative values), clamp to 0..255."""
    return np.clip(np.floor(np.asarray(x, np.float64) + 0.5), 0, 255).astype(np.uint8)


def unorm(v: np.ndarray, bits: int) -> np.ndarray:
    """``v`` in [0, 1] on ``bits`` bits (round to nearest, clamped)."""
    t = (1 << bits) - 1
    return np.clip(np.floor(np.asarray(v, np.float64) * t + 0.5), 0, t).astype(np.uint32)


def scene_arrays(scene: GaussianScene) -> dict[str, Optional[np.ndarray]]:
    """The scene as numpy arrays: ``means``, ``log_scales``, ``quats`` (wxyz, normalised, float64),
    ``opacity`` (logits), ``sh_dc``, ``sh_rest`` ([N, K, 3] or None)."""
    def f32(t):
        return None if t is None else t.detach().to("cpu").float().numpy()

    q = f32(scene.quats).astype(np.float64)
    return {"means": f32(scene.means), "log_scales": f32(scene.log_scales),
            "quats": q / np.linalg.norm(q, axis=1, keepdims=True), "opacity": f32(scene.logit_opacities),
            "sh_dc": f32(scene.sh_dc), "sh_rest": f32(scene.sh_rest)}


def arrays_scene(means, log_scales, quats, opacity, sh_dc, sh_rest=None) -> GaussianScene:
    """A :class:`GaussianScene` (float32) of numpy arrays; ``sh_rest`` [N, K, 3] with K = 3, 8, 15, or None."""
    import torch

    def t(a):
        return torch.from_numpy(np.array(a, dtype=np.float32))   # a copy: the sources may be read-only buffers

    k = 0 if sh_rest is None else int(sh_rest.shape[1])
    degree = {0: 0, 3: 1, 8: 2, 15: 3}[k]
    return GaussianScene(t(means), t(log_scales), t(quats), t(opacity).reshape(-1), t(sh_dc),
                         t(sh_rest) if k else None, None, degree)


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file (an interrupted write leaves nothing)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting ``points [N, 3]`` along a Z-order curve (10 bits an axis over their bounding box)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    cells = np.clip(((points - lo) / span * 1023.0).astype(np.int64), 0, 1023)

    def spread(v):   # bit i of v -> bit 3i
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = (spread(cells[:, 0]) << 2) | (spread(cells[:, 1]) << 1) | spread(cells[:, 2])
    return np.argsort(code, kind="stable")
