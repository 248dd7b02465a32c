"""Pinhole cameras in the convention the rasterizer uses.

Convention (same as gsplat and COLMAP/OpenCV): camera axes x right, y down,
z forward; ``viewmats`` are world-to-camera 4x4 matrices; ``Ks`` are 3x3
intrinsics in pixels for images of ``width`` x ``height``; pixel centres are
at integer + 0.5.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import torch

from ..errors import InputError
from .fileio import read_json, write_json


@dataclass
class Cameras:
    """A set of C pinhole cameras sharing one image size.

    Attributes:
        viewmats: ``[C, 4, 4]`` world-to-camera.
        Ks: ``[C, 3, 3]`` intrinsics.
        width, height: image size in pixels.
        names: one name per camera (usually the image file stem).
    """

    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.viewmats.ndim != 3 or self.viewmats.shape[1:] != (4, 4):
            raise InputError(f"Cameras: viewmats must be [C, 4, 4], got {tuple(self.viewmats.shape)}")
        if self.Ks.shape != (self.viewmats.shape[0], 3, 3):
            raise InputError(f"Cameras: Ks must be [C, 3, 3] with C={self.viewmats.shape[0]}, got {tuple(self.Ks.shape)}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"Cameras: bad image size {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)
        if not self.names:
            self.names = [f"{i:04d}" for i in range(len(self))]
        if len(self.names) != len(self):
            raise InputError(f"Cameras: {len(self.names)} names for {len(self)} cameras")

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def __getitem__(self, idx) -> "Cameras":
        """Cameras at ``idx`` (an int, a slice, a list or a bool/long tensor)."""
        if isinstance(idx, int):
            idx = [idx]
        if isinstance(idx, slice):
            ids = list(range(len(self)))[idx]
        elif isinstance(idx, torch.Tensor):
            ids = torch.arange(len(self))[idx.cpu()].tolist() if idx.dtype == torch.bool else idx.cpu().tolist()
        else:
            ids = list(idx)
        # (copied without waiting for the device: a blocking host-to-device copy synchronises the
        # stream, which a training step pays once per view batch)
        ids_t = torch.as_tensor(ids, dtype=torch.long).to(self.viewmats.device, non_blocking=True)
        return Cameras(self.viewmats[ids_t], self.Ks[ids_t], self.width, self.height, [self.names[i] for i in ids])

    def to(self, device=None, dtype=None) -> "Cameras":
        return Cameras(self.viewmats.to(device=device, dtype=dtype), self.Ks.to(device=device, dtype=dtype),
                       self.width, self.height, list(self.names))

    @property
    def device(self) -> torch.device:
        return self.viewmats.device

    @property
    def camtoworlds(self) -> torch.Tensor:
        """``[C, 4, 4]`` camera-to-world."""
        return torch.linalg.inv_ex(self.viewmats).inverse  # no singularity check: no device sync

    @property
    def centers(self) -> torch.Tensor:
        """``[C, 3]`` camera centres in world space."""
        return self.camtoworlds[:, :3, 3]

    @property
    def forwards(self) -> torch.Tensor:
        """``[C, 3]`` unit viewing directions (camera +z) in world space."""
        return self.camtoworlds[:, :3, 2]

    def rescaled(self, width: int, height: int) -> "Cameras":
        """The same cameras for images resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        Ks = self.Ks.clone()
        Ks[:, 0, :] *= sx
        Ks[:, 1, :] *= sy
        return Cameras(self.viewmats.clone(), Ks, width, height, list(self.names))

    # -- files ---------------------------------------------------------------
    def to_json(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "convention": "opencv: x right, y down, z forward; viewmat = world-to-camera",
            "cameras": [
                {"name": n, "viewmat": v.tolist(), "K": k.tolist()}
                for n, v, k in zip(self.names, self.viewmats.double().cpu(), self.Ks.double().cpu())
            ],
        }

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_json())

    @classmethod
    def from_json(cls, d: dict, dtype=torch.float32) -> "Cameras":
        try:
            cams = d["cameras"]
            viewmats = torch.tensor([c["viewmat"] for c in cams], dtype=dtype).reshape(-1, 4, 4)
            Ks = torch.tensor([c["K"] for c in cams], dtype=dtype).reshape(-1, 3, 3)
            return cls(viewmats, Ks, int(d["width"]), int(d["height"]), [str(c["name"]) for c in cams])
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise InputError(f"cameras file: unexpected layout ({e})") from None

    @classmethod
    def load(cls, path: str | Path, dtype=torch.float32) -> "Cameras":
        return cls.from_json(read_json(path), dtype=dtype)


def look_at(eyes: torch.Tensor, targets: torch.Tensor, up: Sequence[float] = (0.0, 0.0, 1.0)) -> torch.Tensor:
    """World-to-camera matrices ``[C, 4, 4]`` for cameras at ``eyes [C, 3]`` looking at ``targets [C, 3]``.

    ``up`` is the world up direction; the camera's y axis points down (OpenCV).
    """
    eyes = torch.as_tensor(eyes, dtype=torch.float64)
    targets = torch.as_tensor(targets, dtype=torch.float64).expand_as(eyes)
    up_t = torch.as_tensor(up, dtype=torch.float64).expand_as(eyes)
    z = torch.nn.functional.normalize(targets - eyes, dim=-1)
    x = torch.nn.functional.normalize(torch.cross(z, up_t, dim=-1), dim=-1)
    y = torch.cross(z, x, dim=-1)
    R = torch.stack([x, y, z], dim=-2)  # rows: camera axes in world
    t = -(R @ eyes[..., None])[..., 0]
    m = torch.eye(4, dtype=torch.float64).repeat(eyes.shape[0], 1, 1)
    m[:, :3, :3] = R
    m[:, :3, 3] = t
    return m


def intrinsics(fx: float, fy: float, cx: float, cy: float, n: int = 1, dtype=torch.float32) -> torch.Tensor:
    """``[n, 3, 3]`` pinhole intrinsics."""
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.repeat(n, 1, 1)
