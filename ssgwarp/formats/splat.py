"""antimatter15's ``.splat``: no header, 32 bytes per Gaussian: position (3 float32), scale (3
float32, linear standard deviations), colour RGBA (4 uint8: ``(0.5 + SH_C0 * f_dc) * 255`` and
``sigmoid(opacity) * 255``), rotation (4 uint8: the unit wxyz quaternion ``q * 128 + 128``);
sorted by ``scale_x * scale_y * scale_z * opacity``, largest first. No SH beyond degree 0.
Coordinates as our PLY (no conversion).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import SH_C0, GaussianScene
from .codec import arrays_scene, logit, scene_arrays, sigmoid, to_u8, write_atomic

SPLAT_BYTES = 32
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == SPLAT_BYTES


def splat_bytes(scene: GaussianScene) -> bytes:
    """The ``.splat`` file of ``scene`` (SH degree 0 only: higher bands are dropped)."""
    a = scene_arrays(scene)
    alpha = sigmoid(a["opacity"])
    order = np.argsort(-(np.exp(a["log_scales"].astype(np.float64).sum(axis=1)) * alpha), kind="stable")
    rec = np.zeros(len(scene), SPLAT_DTYPE)
    rec["position"] = a["means"][order]
    rec["scale"] = np.exp(np.maximum(a["log_scales"][order].astype(np.float64), -80.0))   # > 0 in float32
    rec["rgba"][:, :3] = to_u8((a["sh_dc"][order].astype(np.float64) * SH_C0 + 0.5) * 255.0)
    rec["rgba"][:, 3] = to_u8(alpha[order] * 255.0)
    rec["rot"] = np.clip(np.floor(a["quats"][order] * 128.0 + 128.5), 0, 255).astype(np.uint8)
    return rec.tobytes()


def write_splat(path: str | Path, scene: GaussianScene) -> Path:
    """Write ``scene`` as an antimatter15 ``.splat`` file, atomically."""
    return write_atomic(path, splat_bytes(scene))


def read_splat(path: str | Path) -> GaussianScene:
    """Read an antimatter15 ``.splat`` file (SH degree 0)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: .splat file not found")
    data = path.read_bytes()
    if not data or len(data) % SPLAT_BYTES:
        raise InputError(f"{path}: not a .splat file ({len(data)} bytes, expected a non-zero multiple of 32)")
    rec = np.frombuffer(data, SPLAT_DTYPE)
    scale = rec["scale"].astype(np.float64)
    if not (np.isfinite(rec["position"]).all() and np.isfinite(scale).all() and (scale > 0).all()):
        raise InputError(f"{path}: .splat file has non-finite positions or non-positive scales (corrupt?)")
    q = (rec["rot"].astype(np.float64) - 128.0) / 128.0
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    rgba = rec["rgba"].astype(np.float64) / 255.0
    return arrays_scene(rec["position"], np.log(scale), q, logit(rgba[:, 3]), (rgba[:, :3] - 0.5) / SH_C0)
