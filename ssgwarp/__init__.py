"""ssgwarp: semantic-aware, structure-preserving 3D style transfer on Gaussian splats.

Public API:
    rasterization        gsplat-compatible differentiable 3DGS renderer (Warp kernels, CPU and CUDA)
    RasterSettings       speed/accuracy knobs of the rasterizer
    GaussianScene        the scene model
    Cameras              pinhole cameras (world-to-camera viewmats, intrinsics)
"""
import os as _os
import sys as _sys

# torch's OpenMP workers busy-wait after every parallel region by default and so take the cores the
# CPU blending's threads need (ssgwarp/raster/cpu_threads.py; measured: half the CPU time of a small
# render's step, docs/notes/benchmarks-history.md). Wait passively instead, unless the user chose a policy. Read once,
# when torch loads: no effect where torch was imported before ssgwarp.
if "torch" not in _sys.modules:
    _os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .core.cameras import Cameras  # noqa: E402
from .errors import InputError, SsgwarpError, WeightsNotFound  # noqa: E402
from .raster.rasterize import RasterSettings, rasterization  # noqa: E402
from .raster.scene import GaussianScene  # noqa: E402

__all__ = ["rasterization", "RasterSettings", "GaussianScene", "Cameras",
           "SsgwarpError", "InputError", "WeightsNotFound"]
__version__ = "0.1.0"
