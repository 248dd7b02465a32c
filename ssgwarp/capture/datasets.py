"""Captures in: COLMAP models, LLFF ``poses_bounds.npy`` and NeRF / instant-ngp ``transforms*.json``.

:func:`load_dataset` auto-detects the layout of a data folder and returns a
:class:`SceneData`: cameras in our convention (OpenCV axes, world-to-camera,
intrinsics at the loaded resolution), the images as one float32 tensor, a
train/test split, and initial points for the Gaussians. Run folders (reading one back, writing
``data.json``) are :mod:`ssgwarp.services.runs`'s. The readers of the layouts are in :mod:`ssgwarp.capture.loaders`.

Layouts, checked in this order:

* ``transforms.json`` or ``transforms_train.json`` (NeRF synthetic, instant-ngp):
  ``camera_angle_x`` (and optional ``camera_angle_y``) or ``fl_x/fl_y/cx/cy``
  (top level or per frame), optional ``k1 k2 k3 p1 p2`` (or fisheye ``k1..k4`` with
  ``is_fisheye`` / ``camera_model: OPENCV_FISHEYE``); ``transform_matrix`` is
  camera-to-world in OpenGL axes (x right, y up, z back) and is converted.
  RGBA images are composited over ``background``. ``transforms_test.json``,
  when present, provides the held-out views (the dataset's own split).
* COLMAP: ``sparse/0`` (or ``sparse``, or the folder itself) with
  ``cameras`` and ``images`` (``.bin`` or ``.txt``); ``points3D`` gives the
  initial points. Every distorted model of :mod:`ssgwarp.capture.lens` is supported.
* LLFF: ``poses_bounds.npy`` ``[N, 17]``: camera-to-world 3x4 in
  [down, right, back] axes, a column ``[H, W, focal]`` at full capture
  resolution (the focal is scaled to the loaded width) and near/far bounds.
  Initial points from ``sparse/0/points3D.bin`` when present, otherwise random
  points inside the near/far bounds of the views. When ``sparse/0/cameras``
  holds a single distorted camera with the poses' focal, its distortion is
  removed too.

Initial points (``init``): ``"auto"`` (the default) takes the capture's own point cloud (COLMAP
``points3D``) and, for a capture without one, triangulates points from its images and known poses
(:mod:`ssgwarp.capture.triangulate`, from the training views only; when fewer than ``MIN_TRIANGULATED`` points survive it says so in one
line and falls back to random points). ``"triangulate"`` triangulates even when the capture has points,
``"random"`` starts from random points (in the views' frusta, or for ``transforms*.json`` in a cube around
the point the cameras look at), ``"capture"`` takes the capture's points or else random ones without
triangulating (quick loads), and a path to a ``.ply`` file loads those points
(:func:`ssgwarp.formats.ply.read_points`). ``SceneData.points_source`` says which it was
(``colmap``, ``triangulated``, ``random``, ``ply``) and ``points_stats`` holds the triangulation's record.

Distorted images become pinhole images in which every pixel has a source
(:func:`ssgwarp.capture.lens.plan_undistortion`: the largest crop of the undistorted
frame, focal lengths kept, one size for all cameras), at the image folder's own
resolution and before any ``width`` resize; ``SceneData.undistortion`` (and
``data.json``) record what was done.

All image I/O goes through :mod:`ssgwarp.core.fileio` (OpenImageIO).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..core.cameras import Cameras
from .loaders import LOADERS, _depth_range, random_points_in_frusta
from .triangulate import scene_depth_range, triangulate
from ..formats.colmap import find_model
from ..errors import InputError
from ..formats.ply import read_points

log = logging.getLogger("ssgwarp.capture.datasets")



@dataclass
class SceneData:
    """A capture ready for training.

    Attributes:
        cameras: all C cameras at the loaded resolution (undistorted pinhole).
        images: ``[C, H, W, 3]`` float32 in [0, 1] (RGBA composited on ``background``).
        names: image names (file names relative to the image folder), one per camera.
        train_ids, test_ids: indices into the cameras.
        points: ``(xyz [P, 3], rgb [P, 3] in [0, 1])`` initial points, or None.
        points_source: "colmap", "triangulated", "random", "ply" (``--init PATH.ply`` or a transforms.json's
            ``ply_file_path``) or "none".
        points_stats: how the points were made: for triangulated points the
            :class:`~ssgwarp.capture.triangulate.Triangulation` stats (count, median reprojection error...).
        near, far: depth range of the scene seen from the cameras (scene units), or None.
        background: RGB the images were composited on (and that renders should use).
        data_dir, image_dir: where the capture and its images live.
        format: "colmap", "llff" or "transforms".
        undistortion: what lens undistortion did (:meth:`ssgwarp.capture.lens.Undistortion.record`: per camera
            its lens, crop box and intrinsics before/after), or None when the capture has no distortion.
        options: the :func:`load_dataset` options that reproduce this data (for ``data.json``).
        masks: ``[C, H, W]`` float32, 1 where a pixel belongs to the scene, 0 where it is left out of losses and
            metrics (nerfstudio ``mask_path``), or None (every pixel counts).
        applied_transform: nerfstudio's 3x4 map from the original COLMAP world to the cameras' world, or None.
    """

    cameras: Cameras
    images: torch.Tensor
    names: list[str]
    train_ids: list[int]
    test_ids: list[int]
    points: Optional[tuple[torch.Tensor, torch.Tensor]] = None
    points_source: str = "none"
    points_stats: dict = field(default_factory=dict)
    near: Optional[float] = None
    far: Optional[float] = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    data_dir: Optional[Path] = None
    image_dir: Optional[str] = None
    format: str = ""
    undistortion: Optional[dict] = None
    options: dict = field(default_factory=dict)
    masks: Optional[torch.Tensor] = None
    applied_transform: Optional[list] = None

    def __post_init__(self) -> None:
        c = len(self.cameras)
        if self.images.shape != (c, self.cameras.height, self.cameras.width, 3):
            raise InputError(f"SceneData: images {tuple(self.images.shape)} do not match {c} cameras of "
                             f"{self.cameras.width}x{self.cameras.height}")
        if len(self.names) != c:
            raise InputError(f"SceneData: {len(self.names)} names for {c} cameras")
        if self.masks is not None and tuple(self.masks.shape) != tuple(self.images.shape[:3]):
            raise InputError(f"SceneData: masks {tuple(self.masks.shape)} do not match images {tuple(self.images.shape)}")

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def undistorted(self) -> bool:
        """True when the images were undistorted (and cropped) at load time."""
        return self.undistortion is not None

    @property
    def metric_frame(self) -> dict:
        """Which image frame metrics on these images are computed in (for ``metrics.json``)."""
        if self.undistortion is None:
            return {"metric_frame": "as-captured", "metric_size": [self.width, self.height]}
        u = self.undistortion
        return {"metric_frame": "undistorted-crop", "metric_size": [self.width, self.height],
                "metric_crop": {"source_size": u["source_size"], "size": u["size"], "resized_to": u.get("resized_to"),
                                "crops": [c["crop"] for c in u["cameras"]]}}

    @property
    def device(self) -> torch.device:
        return self.images.device

    @property
    def width(self) -> int:
        return self.cameras.width

    @property
    def height(self) -> int:
        return self.cameras.height

    @property
    def extent(self) -> float:
        """Scene radius for learning rates and densification: 1.1 x the largest camera distance
        from the camera centroid (the 3DGS definition; at least 1e-3)."""
        c = self.cameras.centers.double()
        r = (c - c.mean(dim=0)).norm(dim=1).max().item() if len(c) > 1 else 0.0
        if r < 1e-6 and self.far is not None:
            r = float(self.far)
        return max(1.1 * r, 1e-3)

    def split(self, which: str) -> list[int]:
        """Camera indices of ``"train"``, ``"test"`` or ``"all"``."""
        if which == "train":
            return list(self.train_ids)
        if which == "test":
            return list(self.test_ids)
        if which == "all":
            return list(range(len(self)))
        raise InputError(f"unknown split '{which}' (train, test or all)")

    def to(self, device) -> "SceneData":
        pts = None if self.points is None else (self.points[0].to(device), self.points[1].to(device))
        masks = None if self.masks is None else self.masks.to(device)
        return replace(self, cameras=self.cameras.to(device), images=self.images.to(device), points=pts, masks=masks)

    def background_tensor(self, channels: int = 3) -> torch.Tensor:
        """``[channels]`` background (RGB then zeros for extra channels) on the data's device."""
        bg = torch.zeros(channels, dtype=torch.float32, device=self.device)
        bg[:3] = torch.tensor(self.background[:3], dtype=torch.float32)
        return bg


# ----------------------------------------------------------------------------- helpers
def _as_path(p) -> Path:
    return Path(p).expanduser()


def detect_layout(path: str | Path) -> str:
    """``"transforms"``, ``"colmap"`` or ``"llff"`` for a data folder (InputError if none fits)."""
    path = _as_path(path)
    if not path.exists():
        raise InputError(f"{path}: data folder not found")
    if not path.is_dir():
        raise InputError(f"{path}: not a folder (give the capture's folder)")
    if (path / "transforms.json").is_file() or (path / "transforms_train.json").is_file():
        return "transforms"
    if find_model(path) is not None:
        return "colmap"
    if (path / "poses_bounds.npy").is_file():
        return "llff"
    raise InputError(f"{path}: no capture found (expected transforms*.json, a COLMAP model in sparse/0 with "
                     f"cameras and images .bin/.txt, or LLFF poses_bounds.npy)")


def _split(n: int, split_every: int, test_mask: Optional[Sequence[bool]] = None) -> tuple[list[int], list[int]]:
    if test_mask is not None:
        test = [i for i in range(n) if test_mask[i]]
    elif split_every and split_every > 0:
        test = [i for i in range(n) if i % split_every == 0]
    else:
        test = []
    train = [i for i in range(n) if i not in set(test)]
    if not train:  # a single image: train on it, hold nothing out
        train, test = list(range(n)), []
    return train, test



INIT_MODES = ("auto", "triangulate", "random", "capture")
MIN_TRIANGULATED = 100  # fewer triangulated points than this: random points instead


def check_init(init) -> "str | Path":
    """``init`` of :func:`load_dataset` checked: one of :data:`INIT_MODES` or the Path of a .ply file."""
    if not isinstance(init, Path) and str(init) in INIT_MODES:
        return str(init)
    p = _as_path(init)
    if p.suffix.lower() != ".ply":
        raise InputError(f"unknown initial points '{init}': use {', '.join(INIT_MODES)} or the path of a .ply "
                         f"point cloud")
    if not p.is_file():
        raise InputError(f"{p}: PLY file of initial points not found")
    return p


def _initial_points(d: dict, init, fmt: str, num_random_points: int, seed: int, progress: bool,
                    train: list[int]) -> None:
    """Set ``d``'s ``points``, ``points_source`` and ``points_stats`` as ``init`` says (module docstring);
    points are triangulated from the ``train`` views only (the held-out views stay unseen)."""
    own = d.get("points_source", "none")
    d["points_stats"] = {}
    if isinstance(init, Path):
        d["points"], d["points_source"] = read_points(init), "ply"
        d["points_stats"] = {"file": str(init.resolve()), "count": len(d["points"][0])}
        return
    if init == "capture" or (init == "auto" and own in ("colmap", "ply")):  # the capture's own points
        return
    cams, imgs = d["cameras"], d["images"]
    if init in ("auto", "triangulate"):
        known = None if fmt == "transforms" or d.get("near") is None else (d["near"], d["far"])
        tri = triangulate(cams[train], imgs[train], names=[d["names"][i] for i in train], progress=progress,
                          depth_range=known)
        if len(tri) >= MIN_TRIANGULATED:
            d["points"], d["points_source"], d["points_stats"] = (tri.xyz, tri.rgb), "triangulated", tri.stats
            if known is None:
                d["near"], d["far"] = _depth_range(tri.xyz.double().numpy(), cams.viewmats.double().numpy())
            return
        why = (f"triangulation kept {len(tri)} points (fewer than {MIN_TRIANGULATED}; {tri.stats['matches']} "
               f"matches in {tri.stats['pairs']} view pairs)")
        log.warning("%s: starting from %d random points instead (--init PATH.ply gives points, --init random "
                    "skips triangulating)", why, num_random_points)
        d["points_stats"] = {"fallback": why, "triangulation": tri.stats}
    if own != "random":
        near, far = d.get("near"), d.get("far")
        if near is None or far is None:
            near, far = scene_depth_range(cams)
        n = len(cams)
        d["points"] = random_points_in_frusta(cams, imgs, np.full(n, near), np.full(n, far), num_random_points, seed)
    d["points_source"] = "random"


def load_dataset(path: str | Path, images: str = "images", split_every: int = 8,
                 background: Sequence[float] = (1.0, 1.0, 1.0), max_images: Optional[int] = None,
                 device=None, *, width: Optional[int] = None, num_random_points: int = 100_000,
                 seed: int = 0, format: Optional[str] = None, init: "str | Path" = "auto",
                 progress: bool = True) -> SceneData:
    """Load a capture (layout auto-detected, see the module docstring).

    Args:
        path: the capture's folder.
        images: image sub-folder (``images``, ``images_4``, ``images_8``...); intrinsics are
            scaled to the size of the images found there.
        split_every: every ``split_every``-th image (0, 8, 16, ...) is held out for testing
            (0: none). A ``transforms_test.json`` overrides this with the dataset's own split.
        background: RGB that RGBA images are composited on.
        max_images: keep at most this many images, evenly spaced (None: all).
        device: where the tensors go (default CPU).
        width: resize the images to this width (height keeps the aspect ratio), after any
            undistortion: the returned images are ``width`` pixels wide.
        num_random_points: initial points when the capture has no point cloud.
        seed: seed of those random points.
        format: force ``"colmap"``, ``"llff"`` or ``"transforms"`` instead of detecting.
        init: initial points: ``"auto"``, ``"triangulate"``, ``"random"``, ``"capture"`` or a ``.ply`` path
            (module docstring).
        progress: progress bars (image loading, triangulation).
    """
    root = _as_path(path)
    fmt = format or detect_layout(root)
    if fmt not in LOADERS:
        raise InputError(f"unknown data format '{fmt}' (colmap, llff or transforms)")
    if split_every is None or split_every < 0:
        raise InputError(f"split_every must be >= 0, got {split_every}")
    bg = tuple(float(v) for v in background)
    if len(bg) != 3:
        raise InputError(f"background must be 3 numbers (RGB), got {background!r}")
    init = check_init(init)
    d = LOADERS[fmt](root, images=images, max_images=max_images, width=width, background=bg,
                      num_random_points=int(num_random_points), seed=seed, progress=progress)
    test_mask = d.pop("test_mask", None)
    train, test = _split(len(d["names"]), split_every, test_mask)
    _initial_points(d, init, fmt, int(num_random_points), seed, progress, train)
    if getattr(width, "at_most", False):      # (a preset's cap: the width the images were loaded at, or none)
        width = int(width) if d["cameras"].width == int(width) else None
    options = dict(images=images, split_every=split_every, background=list(bg), max_images=max_images,
                   width=width, num_random_points=int(num_random_points), seed=seed, format=fmt, init=str(init))
    data = SceneData(train_ids=train, test_ids=test, background=bg, data_dir=root.resolve(), format=fmt,
                     options=options, **d)
    log.info("loaded %s capture %s: %d images %dx%d (%d train, %d test), %s points", fmt, root, len(data),
             data.width, data.height, len(train), len(test),
             "no" if data.points is None else f"{len(data.points[0])} {data.points_source}")
    return data.to(device) if device is not None else data
