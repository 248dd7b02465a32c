"""An environment colour field: what lies behind all the splats (the sky), a colour per viewing direction.

:class:`Environment` holds a small latitude-longitude grid of colours (``[3, rows, cols]``, elevation about the
world's z axis from -90 to +90 degrees, azimuth around it; bilinear between cells, wrapping in azimuth).
A render composites it where the splats leave light through: ``colour + (1 - alpha) * env(direction)``, in
place of the constant background. It is trained with the scene (``reconstruct --sky``,
:mod:`ssgwarp.reconstruction.sky`) and written beside it as ``environment.json`` (a PLY holds Gaussians only);
``ssgwarp render`` composites it when the run has one.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch

FORMAT = "ssgwarp-environment/1"


def ray_directions(cameras) -> torch.Tensor:
    """``[C, H, W, 3]`` unit world-space directions of the pixel centres of ``cameras`` (pinhole, OpenCV axes)."""
    dev = cameras.viewmats.device
    H, W = cameras.height, cameras.width
    v, u = torch.meshgrid(torch.arange(H, device=dev, dtype=torch.float32) + 0.5,
                          torch.arange(W, device=dev, dtype=torch.float32) + 0.5, indexing="ij")
    K = cameras.Ks.float()
    x = (u[None] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (v[None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    d = torch.stack([x, y, torch.ones_like(x)], -1)                 # camera axes
    R = cameras.viewmats[:, :3, :3].float()                          # world -> camera
    d = torch.einsum("cij,chwi->chwj", R, d)                         # R^T d: camera -> world
    return torch.nn.functional.normalize(d, dim=-1)


def sample(grid: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear colours ``[..., 3]`` of the lat-long ``grid [3, rows, cols]`` at unit directions ``dirs [..., 3]``."""
    shape = dirs.shape[:-1]
    d = dirs.reshape(-1, 3)
    az = torch.atan2(d[:, 1], d[:, 0])                                # -pi..pi
    el = torch.asin(d[:, 2].clamp(-1.0, 1.0))                          # -pi/2..pi/2
    rows, cols = grid.shape[1:]
    # wrap in azimuth: one column of the other side on each side, the sample coordinates scaled to match
    g = torch.cat([grid[:, :, -1:], grid, grid[:, :, :1]], dim=2)
    gx = (az / math.pi) * cols / (cols + 2)
    gy = -(el / (math.pi / 2))                                         # row 0: the zenith
    pts = torch.stack([gx, gy], -1)[None, None]                        # [1, 1, N, 2]
    out = torch.nn.functional.grid_sample(g[None], pts, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0].T.reshape(*shape, 3)


class Environment:
    """A colour per direction (module docstring); ``grid [3, rows, cols]`` (a parameter while training)."""

    def __init__(self, grid: torch.Tensor):
        if grid.ndim != 3 or grid.shape[0] != 3:
            raise ValueError(f"Environment: grid must be [3, rows, cols], got {tuple(grid.shape)}")
        self.grid = grid

    @classmethod
    def constant(cls, color, rows: int = 16, cols: int = 32, device=None) -> "Environment":
        c = torch.as_tensor(color, dtype=torch.float32, device=device).reshape(3, 1, 1)
        return cls(c.expand(3, rows, cols).clone())

    def colors(self, cameras) -> torch.Tensor:
        """``[C, H, W, 3]`` environment colours seen by ``cameras``' pixels."""
        return sample(self.grid.clamp(0.0, 1.0), ray_directions(cameras).to(self.grid.device))

    def composite(self, color: torch.Tensor, alpha: torch.Tensor, cameras) -> torch.Tensor:
        """``color [C, H, W, 3]`` (premultiplied, rendered on black) + ``(1 - alpha) env``."""
        return color + (1.0 - alpha) * self.colors(cameras)

    def save(self, path: str | Path) -> None:
        from ..core.fileio import write_json

        g = self.grid.detach().float().cpu().clamp(0.0, 1.0)
        write_json(path, {"format": FORMAT, "rows": g.shape[1], "cols": g.shape[2],
                          "axes": "rows: elevation about world +z from +90 (row 0) to -90 degrees; cols: azimuth "
                                  "atan2(y, x) from -180 to +180 degrees; cell centres; RGB in [0, 1]",
                          "rgb": [[[round(float(v), 5) for v in row] for row in ch] for ch in g]})

    @classmethod
    def load(cls, path: str | Path, device=None) -> "Environment":
        from ..errors import InputError

        d = json.loads(Path(path).read_text())
        if d.get("format") != FORMAT:
            raise InputError(f"{path}: not an environment file (format {d.get('format')!r}, {FORMAT!r} expected)")
        return cls(torch.tensor(d["rgb"], dtype=torch.float32, device=device))
