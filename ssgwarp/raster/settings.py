"""Settings and argument checks of the rasterizer: a leaf module (torch only, no Warp).

:class:`RasterSettings` (the speed/accuracy knobs), the render modes, the default tile size per
device, the transmittance floor per precision, the host-side shape/device/dtype checks
(:func:`check_shapes`) and the errors of the value checks (:func:`raise_for_flags`, whose flag
slots the Warp check kernels in ``kernels/validate.py`` and the torch check in
:func:`ssgwarp.raster.reference.check_values_reference` both fill). :mod:`ssgwarp.raster.rasterize`,
:mod:`ssgwarp.raster.reference` and :mod:`ssgwarp.raster.ops` import from here, never from each other's
settings.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import torch

# flag slots of the value checks (the same as kernels/validate.py, held equal by a test):
# 0..7 NaN/Inf in the input of that position in INPUTS, then the range checks
INPUTS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "backgrounds")
ZERO_QUAT, NEGATIVE_SCALE, OPACITY_RANGE, FOCAL = 8, 9, 10, 11
N_FLAGS = 12


@dataclass(frozen=True)
class RasterSettings:
    """Speed/accuracy knobs of the rasterizer (defaults = gsplat classic mode).

    alpha_min: contributions with alpha below it are skipped, and Gaussians
        whose opacity is below it are culled (gsplat: 1/255).
    t_min: transmittance cut-off: the Gaussian that would bring T to
        ``<= t_min`` ends the pixel and is not blended (gsplat: 1e-4).
    alpha_max: alpha clamp (gsplat: 0.999).
    extent: ``"opacity"``: per-axis radius of ``min(sigma_max, sqrt(2 ln(opacity /
        alpha_min)))`` standard deviations (gsplat); ``"fixed"``: ``sigma_max``.
    sigma_max: the extent cap in standard deviations (gsplat: 3.33).
    fast_math: CUDA float32 kernels use the GPU's approximate ``exp``, ``log``, division and
        square roots (relative error ~1e-6; see docs/tradeoffs.md), as gsplat compiles its
        kernels; ``False``: IEEE maths. No effect on the CPU or in float64. The forward and
        backward passes always share one rule, so the gating decisions match either way.
    covariance: how the projection forms the 2D covariance. ``"gsplat"``: ``J Sigma J^T``
        with gsplat's order of operations, so float32 CUDA images equal gsplat's; loses very
        anisotropic Gaussians (ratio of scales beyond ~1e3) in float32 to cancellation.
        ``"factor"``: from its 2x3 factor with a cancellation-free determinant (accurate at
        anisotropy 1e6 in float32; docs/numerics.md). Same values in exact arithmetic.
    cpu_threads: threads the CPU kernels run on: the blending (forward and backward), each launch
        covering a run of whole tiles, and the projection, SH colours and binning, each launch a run
        of elements; ``None``: ``torch.get_num_threads()`` (``OMP_NUM_THREADS``,
        ``torch.set_num_threads``). Capped by the number of tiles / elements and by the work (small
        images stay on one thread; :mod:`ssgwarp.raster.cpu_threads`). Images, the projection's
        outputs and gradients and the deterministic backward's gradients are bit-identical for any
        count; the default blending backward's gradients differ by float rounding (per-thread sums
        added afterwards). No effect on CUDA.
    """

    alpha_min: float = 1.0 / 255.0
    t_min: float = 1e-4
    alpha_max: float = 0.999
    extent: Literal["opacity", "fixed"] = "opacity"
    sigma_max: float = 3.33
    fast_math: bool = True
    covariance: Literal["gsplat", "factor"] = "gsplat"
    cpu_threads: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha_min < 1.0:
            raise ValueError(f"RasterSettings.alpha_min must be in [0, 1), got {self.alpha_min}")
        if not 0.0 <= self.t_min < 1.0:
            raise ValueError(f"RasterSettings.t_min must be in [0, 1), got {self.t_min}")
        if not 0.0 < self.alpha_max <= 1.0:
            raise ValueError(f"RasterSettings.alpha_max must be in (0, 1], got {self.alpha_max}")
        if self.extent not in ("opacity", "fixed"):
            raise ValueError(f"RasterSettings.extent must be 'opacity' or 'fixed', got {self.extent!r}")
        if self.covariance not in ("gsplat", "factor"):
            raise ValueError(f"RasterSettings.covariance must be 'gsplat' or 'factor', got {self.covariance!r}")
        if not self.sigma_max > 0.0:
            raise ValueError(f"RasterSettings.sigma_max must be > 0, got {self.sigma_max}")
        if self.cpu_threads is not None and (type(self.cpu_threads) is not int or self.cpu_threads < 1):
            raise ValueError(f"RasterSettings.cpu_threads must be None or an int >= 1, got {self.cpu_threads!r}")

    def for_dtype(self, dtype: torch.dtype) -> "RasterSettings":
        """These settings with ``t_min`` raised to the precision's floor (see ``T_MIN_FLOOR``)."""
        floor = T_MIN_FLOOR.get(dtype, 0.0)
        if self.t_min >= floor:
            return self
        return dataclasses.replace(self, t_min=floor)

    @classmethod
    def exact(cls, sigma_max: float = 3.33) -> "RasterSettings":
        """No alpha threshold, no transmittance cut-off, no alpha clamp, IEEE maths and the
        cancellation-free covariance (gradient checks, extreme scenes)."""
        return cls(alpha_min=0.0, t_min=0.0, alpha_max=1.0, extent="fixed", sigma_max=sigma_max, fast_math=False,
                   covariance="factor")


RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
_DEFAULT_SETTINGS = RasterSettings()

# tile size when the caller gives none, per device type: gsplat's 16 on CUDA (its layout, and the
# fastest forward+backward there); 8 on the CPU, where a pixel walks its whole tile's list one
# Gaussian at a time, so shorter lists win (measured 1.6-3x faster than 16; benchmarks/raster.py --tile,
# docs/tradeoffs.md). Under the default rules the image does not depend on the tile size.
DEFAULT_TILE_SIZE = {"cuda": 16, "cpu": 8}

# Pixels always end once the transmittance would fall to this floor, also with t_min = 0: layers
# behind it add less than the precision resolves, and the backward pass rebuilds each layer's
# transmittance from the final one by division, which needs the final one well inside the normal
# range of the type (float32 denormals start at 1.2e-38).
T_MIN_FLOOR = {torch.float32: 1e-20, torch.float64: 1e-200}


# gsplat's camera models that ssgwarp does not render, and what to do instead
UNSUPPORTED_CAMERA_MODELS = {
    "ortho": "orthographic projection is not implemented; use a pinhole camera with a long focal length "
             "placed far away",
    "fisheye": "undistort the images to pinhole first (e.g. colmap image_undistorter; ssgwarp's capture "
               "readers undistort OPENCV_FISHEYE captures on loading, docs/data.md)",
    "ftheta": "undistort the images to pinhole first (e.g. colmap image_undistorter)",
}


def check_camera_model(camera_model) -> None:
    """``"pinhole"`` passes; gsplat's other models (ortho, fisheye, ftheta) and anything else raise
    one ValueError each, saying what to do instead."""
    if camera_model == "pinhole":
        return
    if camera_model in UNSUPPORTED_CAMERA_MODELS:
        raise ValueError(f"rasterization: camera_model={camera_model!r} is not supported (pinhole only): "
                         f"{UNSUPPORTED_CAMERA_MODELS[camera_model]}")
    raise ValueError(f"rasterization: camera_model must be 'pinhole' (gsplat's 'ortho', 'fisheye' and 'ftheta' "
                     f"are not supported), got {camera_model!r}")


def resolve_arguments(means, settings, tile_size, camera_model="pinhole") -> tuple:
    """``(settings, tile_size)`` of a rasterizer call: the settings (default: gsplat's rules) for
    the dtype of ``means`` (:meth:`RasterSettings.for_dtype`), the tile size (default: per device,
    :data:`DEFAULT_TILE_SIZE`) as an int; a camera model other than pinhole is refused
    (:func:`check_camera_model`)."""
    check_camera_model(camera_model)
    settings = (settings or _DEFAULT_SETTINGS).for_dtype(means.dtype)
    if tile_size is None:
        tile_size = DEFAULT_TILE_SIZE.get(means.device.type, 16)
    return settings, int(tile_size)


def raise_for_flags(flags: list) -> None:
    """Raise the ValueError of the first failed value check (``flags``: the host copy of the
    flags of :func:`ssgwarp.raster.ops.check_values` or :func:`ssgwarp.raster.reference.check_values_reference`)."""
    if not any(flags):
        return
    for slot, n in enumerate(INPUTS):
        if flags[slot]:
            raise ValueError(f"rasterization: {n} has NaN/Inf values")
    if flags[ZERO_QUAT]:
        raise ValueError("rasterization: quats has zero quaternions (rotation undefined)")
    if flags[NEGATIVE_SCALE]:
        raise ValueError("rasterization: scales has negative values (scales are linear, >= 0)")
    if flags[OPACITY_RANGE]:
        raise ValueError("rasterization: opacities must lie in [0, 1] (apply a sigmoid to logits)")
    if flags[FOCAL]:
        raise ValueError("rasterization: Ks has non-positive focal lengths")


def check_shapes(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree, backgrounds,
                 render_mode, rasterize_mode, tile_size, near_plane=0.01) -> None:
    """The shape, device, dtype and argument checks of :func:`validate_inputs` (host only)."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities,
             "colors": colors, "viewmats": viewmats, "Ks": Ks}
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    for name, t in named.items():
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"rasterization: {name} must be a torch.Tensor, got {type(t).__name__}")
    dev, dt = means.device, means.dtype
    if dt not in (torch.float32, torch.float64):
        raise ValueError(f"rasterization: means must be float32 or float64, got {dt}")
    for name, t in named.items():
        if t.device != dev:
            raise ValueError(f"rasterization: {name} is on {t.device} but means is on {dev}")
        if t.dtype != dt:
            raise ValueError(f"rasterization: {name} is {t.dtype} but means is {dt} (use one dtype)")
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterization: means must be [N, 3], got {tuple(means.shape)}")
    N = means.shape[0]
    if quats.shape != (N, 4):
        raise ValueError(f"rasterization: quats must be [N={N}, 4], got {tuple(quats.shape)}")
    if scales.shape != (N, 3):
        raise ValueError(f"rasterization: scales must be [N={N}, 3], got {tuple(scales.shape)}")
    if opacities.shape != (N,):
        raise ValueError(f"rasterization: opacities must be [N={N}], got {tuple(opacities.shape)}")
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"rasterization: viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if Ks.shape != (C, 3, 3):
        raise ValueError(f"rasterization: Ks must be [C={C}, 3, 3], got {tuple(Ks.shape)}")
    if sh_degree is None:
        if not ((colors.ndim == 2 and colors.shape[0] == N) or (colors.ndim == 3 and colors.shape[:2] == (C, N))):
            raise ValueError(f"rasterization: colors must be [N={N}, D] or [C={C}, N, D], got {tuple(colors.shape)}")
        if colors.shape[-1] < 1:
            raise ValueError("rasterization: colors has zero channels")
    else:
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"rasterization: sh_degree must be 0..3, got {sh_degree}")
        ok = (colors.ndim == 3 and colors.shape[0] == N) or (colors.ndim == 4 and colors.shape[:2] == (C, N))
        if not ok or colors.shape[-1] != 3 or colors.shape[-2] < (sh_degree + 1) ** 2:
            raise ValueError(f"rasterization: with sh_degree={sh_degree} colors must be [N={N}, K>={(sh_degree + 1) ** 2}, 3]"
                             f" (or [C, N, K, 3]), got {tuple(colors.shape)}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"rasterization: width and height must be positive, got {width}x{height}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"rasterization: render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterization: rasterize_mode must be 'classic' or 'antialiased', got {rasterize_mode!r}")
    if not near_plane > 0:
        raise ValueError(f"rasterization: near_plane must be > 0, got {near_plane}")
    if int(tile_size) <= 0 or int(tile_size) > 64:
        raise ValueError(f"rasterization: tile_size must be in 1..64, got {tile_size}")
