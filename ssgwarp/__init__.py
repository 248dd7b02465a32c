"""ssgwarp: semantic-aware, structure-preserving 3D style transfer on Gaussian splats.

Public API:
    rasterization        gsplat-compatible differentiable 3DGS renderer (Warp kernels, CPU and CUDA)
    RasterSettings       speed/accuracy knobs of the rasterizer
    GaussianScene        the scene model
    Cameras              pinhole cameras (world-to-camera viewmats, intrinsics)
"""
from .core.cameras import Cameras
from .errors import InputError, SsgwarpError, WeightsNotFound
from .raster.rasterize import RasterSettings, rasterization
from .raster.scene import GaussianScene

__all__ = ["rasterization", "RasterSettings", "GaussianScene", "Cameras",
           "SsgwarpError", "InputError", "WeightsNotFound"]
__version__ = "0.1.0"
