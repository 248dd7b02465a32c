"""ssgwarp: semantic-aware, structure-preserving 3D style transfer on Gaussian splats.

Public API:
    rasterization        gsplat-compatible differentiable 3DGS renderer (Warp kernels, CPU and CUDA)
    RasterSettings       speed/accuracy knobs of the rasterizer
    GaussianScene        the scene model
    Cameras              pinhole cameras (world-to-camera viewmats, intrinsics)

Importing the package changes nothing in the process (no environment variable, no ``sys.path`` entry) and
loads no heavy library: the names above are loaded from their modules when first used (PEP 562), so that the
``ssgwarp`` command can choose torch's OpenMP wait policy before torch loads (``ssgwarp.cli.main``).
"""
from __future__ import annotations

import importlib as _importlib

from .errors import InputError, SsgwarpError, WeightsNotFound

# public name -> the module that defines it
_LAZY = {"rasterization": "ssgwarp.raster.rasterize", "RasterSettings": "ssgwarp.raster.settings",
         "GaussianScene": "ssgwarp.raster.scene", "Cameras": "ssgwarp.core.cameras"}

__all__ = ["rasterization", "RasterSettings", "GaussianScene", "Cameras",
           "SsgwarpError", "InputError", "WeightsNotFound"]
__version__ = "0.1.0"


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'ssgwarp' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value   # (looked up once)
    return value


def __dir__() -> list:
    return sorted(set(globals()) | set(__all__))
