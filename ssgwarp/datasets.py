"""Captures in: COLMAP models, LLFF ``poses_bounds.npy`` and NeRF / instant-ngp ``transforms*.json``.

:func:`load_dataset` auto-detects the layout of a data folder and returns a
:class:`SceneData`: cameras in our convention (OpenCV axes, world-to-camera,
intrinsics at the loaded resolution), the images as one float32 tensor, a
train/test split, and initial points for the Gaussians. :func:`load_run` reads
a reconstruction run directory back (scene + the data it was trained on).

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
  initial points. Every distorted model of :mod:`ssgwarp.lens` is supported.
* LLFF: ``poses_bounds.npy`` ``[N, 17]``: camera-to-world 3x4 in
  [down, right, back] axes, a column ``[H, W, focal]`` at full capture
  resolution (the focal is scaled to the loaded width) and near/far bounds.
  Initial points from ``sparse/0/points3D.bin`` when present, otherwise random
  points inside the near/far bounds of the views. When ``sparse/0/cameras``
  holds a single distorted camera with the poses' focal, its distortion is
  removed too.

Distorted images become pinhole images in which every pixel has a source
(:func:`ssgwarp.lens.plan_undistortion`: the largest crop of the undistorted
frame, focal lengths kept, one size for all cameras), at the image folder's own
resolution and before any ``width`` resize; ``SceneData.undistortion`` (and
``data.json``) record what was done.

All image I/O goes through :mod:`ssgwarp.fileio` (OpenImageIO).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from .cameras import Cameras
from .errors import InputError

log = logging.getLogger("ssgwarp.datasets")

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp", ".PNG", ".JPG", ".JPEG")
# OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class SceneData:
    """A capture ready for training.

    Attributes:
        cameras: all C cameras at the loaded resolution (undistorted pinhole).
        images: ``[C, H, W, 3]`` float32 in [0, 1] (RGBA composited on ``background``).
        names: image names (file names relative to the image folder), one per camera.
        train_ids, test_ids: indices into the cameras.
        points: ``(xyz [P, 3], rgb [P, 3] in [0, 1])`` initial points, or None.
        points_source: "colmap", "random" or "none".
        near, far: depth range of the scene seen from the cameras (scene units), or None.
        background: RGB the images were composited on (and that renders should use).
        data_dir, image_dir: where the capture and its images live.
        format: "colmap", "llff" or "transforms".
        undistortion: what lens undistortion did (:meth:`ssgwarp.lens.Undistortion.record`: per camera
            its lens, crop box and intrinsics before/after), or None when the capture has no distortion.
        options: the :func:`load_dataset` options that reproduce this data (for ``data.json``).
    """

    cameras: Cameras
    images: torch.Tensor
    names: list[str]
    train_ids: list[int]
    test_ids: list[int]
    points: Optional[tuple[torch.Tensor, torch.Tensor]] = None
    points_source: str = "none"
    near: Optional[float] = None
    far: Optional[float] = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    data_dir: Optional[Path] = None
    image_dir: Optional[str] = None
    format: str = ""
    undistortion: Optional[dict] = None
    options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        c = len(self.cameras)
        if self.images.shape != (c, self.cameras.height, self.cameras.width, 3):
            raise InputError(f"SceneData: images {tuple(self.images.shape)} do not match {c} cameras of "
                             f"{self.cameras.width}x{self.cameras.height}")
        if len(self.names) != c:
            raise InputError(f"SceneData: {len(self.names)} names for {c} cameras")

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
        return replace(self, cameras=self.cameras.to(device), images=self.images.to(device), points=pts)

    def background_tensor(self, channels: int = 3) -> torch.Tensor:
        """``[channels]`` background (RGB then zeros for extra channels) on the data's device."""
        bg = torch.zeros(channels, dtype=torch.float32, device=self.device)
        bg[:3] = torch.tensor(self.background[:3], dtype=torch.float32)
        return bg


# ----------------------------------------------------------------------------- helpers
def _as_path(p) -> Path:
    return Path(p).expanduser()


def detect_format(path: str | Path) -> str:
    """``"transforms"``, ``"colmap"`` or ``"llff"`` for a data folder (InputError if none fits)."""
    from .colmap import find_model

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


def _image_folder(root: Path, images: str) -> Path:
    folder = root / images
    if folder.is_dir():
        return folder
    avail = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("images"))
    hint = f"; available: {', '.join(avail)} (pass --images {avail[-1]})" if avail else ""
    raise InputError(f"{folder}: image folder not found{hint}")


def _list_images(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_EXTS
                  and not p.name.startswith("."))


def _resolve_image(folder: Path, name: str) -> Optional[Path]:
    """``folder/name``, or the same stem with another image extension (``images_N`` often re-encode)."""
    p = folder / name
    if p.is_file():
        return p
    stem = Path(name)
    stem = stem.with_suffix("") if stem.suffix else stem
    for ext in IMAGE_EXTS:
        q = folder / (str(stem) + ext)
        if q.is_file():
            return q
    return None


def _missing_error(missing: Sequence[str], folder: Path, source: str) -> InputError:
    shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
    return InputError(f"{len(missing)} image(s) referenced by {source} are missing from {folder}: {shown}")


def _evenly(n: int, k: Optional[int]) -> list[int]:
    if k is None or k >= n:
        return list(range(n))
    if k <= 0:
        raise InputError(f"max_images must be positive, got {k}")
    return sorted(set(np.linspace(0, n - 1, k).round().astype(int).tolist()))


def _load_images(paths: Sequence[Path], background, width: Optional[int],
                 intrinsics: Callable) -> tuple[torch.Tensor, torch.Tensor, Optional[dict]]:
    """Read, composite RGBA, remove lens distortion and resize, one image at a time.

    ``intrinsics(w0, h0)`` gives, for files of ``w0`` x ``h0`` pixels, ``(Ks [C, 3, 3] float64,
    lenses [C] (:class:`~ssgwarp.lens.Lens` or None), labels [C] (each image's camera, for errors))``.
    Distorted images become the pinhole crop of :func:`ssgwarp.lens.plan_undistortion` (at the files'
    resolution, before any resize). Returns ``(images [C, H, W, 3], Ks [C, 3, 3] float64 of those
    images, the undistortion record or None)``.
    """
    from .fileio import read_image
    from .lens import plan_undistortion

    from tqdm import tqdm

    if width is not None and width <= 0:
        raise InputError(f"width must be positive, got {width}")
    out = []
    size0 = plan = Ks = None
    h = w = hu = wu = 0
    bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
    it = tqdm(paths, desc="loading images", unit="img", leave=False, disable=len(paths) < 16)
    for i, p in enumerate(it):
        img = read_image(p)
        if img.shape[2] == 1 or img.shape[2] == 2:
            img = np.concatenate([np.repeat(img[..., :1], 3, axis=2), img[..., 1:]], axis=2)
        if img.shape[2] >= 4:
            # OpenImageIO hands back associated (premultiplied) alpha: over-composite is rgb + (1 - a) * bg
            a = np.clip(img[..., 3:4], 0.0, 1.0)
            img = img[..., :3] + (1.0 - a) * bg
        img = np.clip(img[..., :3], 0.0, 1.0)
        if size0 is None:
            size0 = img.shape[:2]
            h0, w0 = size0
            Ks, lenses, labels = intrinsics(w0, h0)
            plan = plan_undistortion(Ks, lenses, w0, h0, labels)
            if plan is not None:
                Ks = plan.Ks
                models = sorted({c.lens.model for c in plan.cameras if c.lens is not None})
                log.info("undistorting %d images (%s) into a %dx%d pinhole crop of the %dx%d images "
                         "(every pixel has a source)", len(paths), "/".join(models), *plan.size, w0, h0)
            wu, hu = plan.size if plan is not None else (w0, h0)
            w, h = (width, max(1, int(round(hu * width / wu)))) if width is not None else (wu, hu)
        elif img.shape[:2] != size0:
            raise InputError(f"{p}: image size {img.shape[1]}x{img.shape[0]} differs from the others "
                             f"({size0[1]}x{size0[0]}); all images of a capture must have one size")
        t = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32))
        if plan is not None:
            t = plan(i, t)
        if (h, w) != (hu, wu):
            t = resize_images(t[None], h, w)[0]
        out.append(t)
    if not out:
        raise InputError("no images to load")
    Ks = np.array(Ks, dtype=np.float64)
    Ks[:, 0, :] *= w / wu
    Ks[:, 1, :] *= h / hu
    record = None
    if plan is not None:
        record = {**plan.record(), "resized_to": [w, h] if (w, h) != (wu, hu) else None}
    return torch.stack(out), torch.from_numpy(Ks), record


def resize_images(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``[C, H, W, 3] -> [C, height, width, 3]`` (area-averaged when shrinking, bilinear otherwise)."""
    x = images.permute(0, 3, 1, 2)
    if height <= images.shape[1] and width <= images.shape[2]:
        x = torch.nn.functional.interpolate(x, size=(height, width), mode="bilinear", antialias=True,
                                            align_corners=False)
    else:
        x = torch.nn.functional.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)
    return x.permute(0, 2, 3, 1).clamp(0.0, 1.0).contiguous()


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


def _viewmats_from_c2w(c2w: np.ndarray) -> torch.Tensor:
    c2w = np.asarray(c2w, dtype=np.float64)
    m = np.tile(np.eye(4), (c2w.shape[0], 1, 1))
    m[:, :3, :4] = c2w[:, :3, :4]
    if not np.all(np.isfinite(m)):
        raise InputError("camera poses contain NaN/inf values")
    return torch.from_numpy(np.linalg.inv(m))


def _depth_range(xyz: np.ndarray, viewmats: np.ndarray) -> tuple[Optional[float], Optional[float]]:
    if xyz is None or len(xyz) == 0:
        return None, None
    rng = np.random.default_rng(0)
    if len(xyz) > 20000:
        xyz = xyz[rng.choice(len(xyz), 20000, replace=False)]
    z = np.einsum("cij,pj->cpi", viewmats[:, :3, :3], xyz)[..., 2] + viewmats[:, None, 2, 3]
    z = z[z > 0]
    if z.size == 0:
        return None, None
    return float(np.percentile(z, 0.1)), float(np.percentile(z, 99.9))


def random_points_in_frusta(cameras: Cameras, images: torch.Tensor, near: np.ndarray, far: np.ndarray,
                            n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points at random pixels of random views, at depths uniform in disparity between each
    view's ``near`` and ``far``; coloured by that pixel. Returns ``(xyz [n,3], rgb [n,3])``."""
    g = torch.Generator().manual_seed(seed)
    c = len(cameras)
    cam = torch.randint(0, c, (n,), generator=g)
    u = torch.rand(n, generator=g, dtype=torch.float64) * cameras.width
    v = torch.rand(n, generator=g, dtype=torch.float64) * cameras.height
    near_t = torch.as_tensor(near, dtype=torch.float64)[cam]
    far_t = torch.as_tensor(far, dtype=torch.float64)[cam]
    t = torch.rand(n, generator=g, dtype=torch.float64)
    depth = 1.0 / (1.0 / near_t * (1 - t) + 1.0 / far_t * t)
    K = cameras.Ks.double().cpu()[cam]
    x = (u - K[:, 0, 2]) / K[:, 0, 0] * depth
    y = (v - K[:, 1, 2]) / K[:, 1, 1] * depth
    p_cam = torch.stack([x, y, depth, torch.ones_like(depth)], dim=1)
    c2w = cameras.camtoworlds.double().cpu()[cam]
    xyz = (c2w @ p_cam[:, :, None])[:, :3, 0]
    rgb = images.cpu()[cam, v.long().clamp(max=cameras.height - 1), u.long().clamp(max=cameras.width - 1)]
    return xyz.float(), rgb.float()


def focus_point(cameras: Cameras) -> torch.Tensor:
    """``[3]`` the point nearest (least squares) to all optical axes."""
    c = cameras.centers.double().cpu()
    d = torch.nn.functional.normalize(cameras.forwards.double().cpu(), dim=1)
    eye = torch.eye(3, dtype=torch.float64)
    A = (eye[None] - d[:, :, None] * d[:, None, :])
    lhs, rhs = A.sum(0), (A @ c[:, :, None]).sum(0)[:, 0]
    if torch.linalg.matrix_rank(lhs) < 3:
        return c.mean(0)
    return torch.linalg.solve(lhs, rhs)


# ----------------------------------------------------------------------------- formats
def _load_colmap(root: Path, images: str, max_images, width, background, **_):
    from .colmap import find_model, read_model

    model = read_model(find_model(root))
    if not model.images:
        raise InputError(f"{model.path}: the COLMAP model has no registered images")
    ims = sorted(model.images.values(), key=lambda im: im.name)
    ims = [ims[i] for i in _evenly(len(ims), max_images)]
    folder = _image_folder(root, images)
    paths, missing = [], []
    for im in ims:
        p = _resolve_image(folder, im.name)
        (missing.append(im.name) if p is None else paths.append(p))
    if missing:
        raise _missing_error(missing, folder, f"{model.path}/images")
    cam_of = [model.cameras[im.camera_id] for im in ims]
    cam_file = next((p for p in (model.path / "cameras.bin", model.path / "cameras.txt") if p.is_file()), model.path)

    def intrinsics(w0, h0):
        Ks = []
        for cam in cam_of:
            K = cam.K.copy()
            K[0] *= w0 / cam.width
            K[1] *= h0 / cam.height
            Ks.append(K)
        return np.stack(Ks), [c.lens for c in cam_of], [f"{cam_file}: camera {c.id}" for c in cam_of]

    imgs, Ks, undist = _load_images(paths, background, width, intrinsics)
    viewmats = np.stack([im.viewmat for im in ims])
    names = [str(p.relative_to(folder)) for p in paths]
    cams = Cameras(torch.from_numpy(viewmats).float(), Ks.float(), imgs.shape[2], imgs.shape[1], names)
    pts = None
    src = "none"
    near = far = None
    if model.points is not None and len(model.points):
        pts = (torch.from_numpy(model.points.xyz).float(), torch.from_numpy(model.points.rgb).float() / 255.0)
        src = "colmap"
        near, far = _depth_range(model.points.xyz, viewmats)
    return dict(cameras=cams, images=imgs, names=names, points=pts, points_source=src, near=near, far=far,
                image_dir=folder.name, undistortion=undist)


def _load_llff(root: Path, images: str, max_images, width, background, num_random_points, seed, **_):
    from .colmap import find_model, read_cameras, read_points3d, _pick

    pb_path = root / "poses_bounds.npy"
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except Exception as e:
        raise InputError(f"{pb_path}: cannot read ({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    if pb.ndim != 2 or pb.shape[1] != 17 or pb.shape[0] == 0:
        raise InputError(f"{pb_path}: poses of the wrong shape {tuple(pb.shape)} (LLFF expects [N, 17]: "
                         f"3x5 pose-and-hwf + near/far per image)")
    if not np.all(np.isfinite(pb)):
        raise InputError(f"{pb_path}: contains NaN/inf values")
    folder = _image_folder(root, images)
    files = _list_images(folder)
    if len(files) != pb.shape[0]:
        raise InputError(f"{pb_path} has {pb.shape[0]} poses but {folder} has {len(files)} images; "
                         f"they must match one to one (sorted by name)")
    keep = _evenly(len(files), max_images)
    files = [files[i] for i in keep]
    pb = pb[keep]
    poses = pb[:, :15].reshape(-1, 3, 5)
    bounds = pb[:, 15:17]
    h_full, w_full, focal = poses[0, 0, 4], poses[0, 1, 4], poses[:, 2, 4]
    # the lens: a single distorted camera in sparse/0 whose focal is the poses' (same capture, same resolution)
    lens, label = None, str(pb_path)
    model = find_model(root)
    cam_file = _pick(root / "sparse" / "0", "cameras") or (model and _pick(model, "cameras"))
    if cam_file:
        ccams = read_cameras(cam_file)
        if len(ccams) == 1:
            cc = next(iter(ccams.values()))
            if cc.model not in ("SIMPLE_PINHOLE", "PINHOLE"):
                if abs(cc.K[0, 0] * w_full / cc.width - focal[0]) <= 0.01 * focal[0]:
                    lens, label = cc.lens, f"{pb_path} with the lens of {cam_file}: camera {cc.id}"
                else:
                    log.warning("%s: camera %d (%s) has another focal length than %s; its distortion is not "
                                "removed", cam_file, cc.id, cc.model, pb_path.name)

    def intrinsics(w0, h0):
        Ks = np.zeros((len(files), 3, 3))
        Ks[:, 0, 0] = focal * (w0 / w_full)
        Ks[:, 1, 1] = focal * (h0 / h_full)
        Ks[:, 0, 2] = w0 / 2.0
        Ks[:, 1, 2] = h0 / 2.0
        Ks[:, 2, 2] = 1.0
        return Ks, [lens] * len(files), [label] * len(files)

    imgs, Ks, undist = _load_images([folder / f for f in files], background, width, intrinsics)
    # [down, right, back] -> [right, down, forward]
    c2w = np.concatenate([poses[:, :, 1:2], poses[:, :, 0:1], -poses[:, :, 2:3], poses[:, :, 3:4]], axis=2)
    viewmats = _viewmats_from_c2w(c2w)
    cams = Cameras(viewmats.float(), Ks.float(), imgs.shape[2], imgs.shape[1], files)

    near, far = float(bounds.min()), float(bounds.max())
    pts_file = _pick(root / "sparse" / "0", "points3D")
    if pts_file is not None:
        p = read_points3d(pts_file)
        pts = (torch.from_numpy(p.xyz).float(), torch.from_numpy(p.rgb).float() / 255.0)
        src = "colmap"
    else:
        pts = random_points_in_frusta(cams, imgs, bounds[:, 0], bounds[:, 1], num_random_points, seed)
        src = "random"
    return dict(cameras=cams, images=imgs, names=files, points=pts, points_source=src, near=near, far=far,
                image_dir=folder.name, undistortion=undist)


def _intrinsics_from(meta: dict, w: int, h: int, where: str) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy at the JSON's own resolution (``meta['w'/'h']`` or the image's)."""
    if not any(k in meta for k in ("fl_x", "fl_y", "camera_angle_x")):
        raise InputError(f"{where}: no intrinsics (need camera_angle_x or fl_x/fl_y)")
    try:
        if "fl_x" in meta or "fl_y" in meta:
            fx = float(meta.get("fl_x", meta.get("fl_y")))
            fy = float(meta.get("fl_y", fx))
        elif "camera_angle_x" in meta:
            fx = 0.5 * w / np.tan(0.5 * float(meta["camera_angle_x"]))
            fy = 0.5 * h / np.tan(0.5 * float(meta["camera_angle_y"])) if "camera_angle_y" in meta else fx
        cx = float(meta.get("cx", w / 2.0))
        cy = float(meta.get("cy", h / 2.0))
    except (TypeError, ValueError):
        raise InputError(f"{where}: intrinsics are not numbers") from None
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise InputError(f"{where}: invalid intrinsics fx={fx} fy={fy}")
    return fx, fy, cx, cy


_TRANSFORMS_MODELS = ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE")


def _transforms_lens(meta: dict, where: str):
    """The lens of a transforms.json camera: ``k1 k2 k3 p1 p2`` (OpenCV, k3 the r^6 term), or with
    instant-ngp's ``is_fisheye`` / nerfstudio's ``camera_model: OPENCV_FISHEYE`` the fisheye ``k1..k4``."""
    from .lens import Lens

    model = str(meta.get("camera_model", "")).upper()
    if model and model not in _TRANSFORMS_MODELS:
        raise InputError(f"{where}: camera_model {meta['camera_model']} is not supported (supported: "
                         f"{', '.join(_TRANSFORMS_MODELS)}); convert the capture to pinhole images first")
    flag = meta.get("is_fisheye", False)
    fisheye = model == "OPENCV_FISHEYE" or (flag.strip().lower() in ("1", "true") if isinstance(flag, str)
                                            else bool(flag))
    try:
        k1, k2, k3, k4, p1, p2 = (float(meta.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    except (TypeError, ValueError):
        raise InputError(f"{where}: distortion coefficients are not numbers") from None
    if fisheye:
        if p1 or p2:
            raise InputError(f"{where}: a fisheye camera (is_fisheye / OPENCV_FISHEYE) takes k1 k2 k3 k4, "
                             f"not p1 p2 (got p1={p1:g} p2={p2:g})")
        return Lens("OPENCV_FISHEYE", (k1, k2, k3, k4))
    if k4:
        raise InputError(f"{where}: k4={k4:g} without is_fisheye: k4 belongs to the fisheye model (set "
                         f"\"is_fisheye\": true or \"camera_model\": \"OPENCV_FISHEYE\") or is not supported")
    if k3:
        return Lens("FULL_OPENCV", (k1, k2, p1, p2, k3, 0.0, 0.0, 0.0))
    return Lens("OPENCV", (k1, k2, p1, p2))


def _load_transforms(root: Path, images: str, max_images, width, background, num_random_points, seed, **_):
    from .fileio import read_json

    if (root / "transforms.json").is_file():
        sources = [(root / "transforms.json", False)]
    else:
        sources = [(root / "transforms_train.json", False)]
        if (root / "transforms_test.json").is_file():
            sources.append((root / "transforms_test.json", True))
    frames, metas, is_test = [], [], []
    for jpath, test in sources:
        meta = read_json(jpath)
        if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
            raise InputError(f"{jpath}: expected an object with a non-empty 'frames' list")
        for i, fr in enumerate(meta["frames"]):
            if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
                raise InputError(f"{jpath}: frame {i} needs 'file_path' and 'transform_matrix'")
            frames.append(fr)
            metas.append((jpath, meta))
            is_test.append(test)
    keep = _evenly(len(frames), max_images)
    frames = [frames[i] for i in keep]
    metas = [metas[i] for i in keep]
    is_test = [is_test[i] for i in keep]

    paths, missing, c2w = [], [], []
    for fr, (jpath, _) in zip(frames, metas):
        rel = Path(str(fr["file_path"]))
        if images != "images" and rel.parts and rel.parts[0] == "images":
            rel = Path(images, *rel.parts[1:])
        p = _resolve_image(root, str(rel))
        (missing.append(str(rel)) if p is None else paths.append(p))
        try:
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{jpath}: transform_matrix of {rel} is not a matrix of numbers") from None
        if m.shape not in ((4, 4), (3, 4)):
            raise InputError(f"{jpath}: transform_matrix of {rel} has the wrong shape {m.shape} (expected 4x4)")
        c2w.append(m[:3, :4])
    if missing:
        raise _missing_error(missing, root, ", ".join(sorted({m[0].name for m in metas})))
    cams_meta = []
    for fr, (jpath, meta), p in zip(frames, metas, paths):
        merged = {**meta, **{k: v for k, v in fr.items() if k not in ("file_path", "transform_matrix")}}
        where = f"{jpath}: frame {p.relative_to(root)}"
        cams_meta.append((merged, where, _transforms_lens(merged, where)))

    def intrinsics(w0, h0):
        Ks = []
        for merged, where, _ in cams_meta:
            jw, jh = int(merged.get("w", w0)), int(merged.get("h", h0))
            fx, fy, cx, cy = _intrinsics_from(merged, jw, jh, where)
            sx, sy = w0 / jw, h0 / jh
            Ks.append([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])
        return np.array(Ks), [c[2] for c in cams_meta], [c[1] for c in cams_meta]

    imgs, Ks, undist = _load_images(paths, background, width, intrinsics)
    c2w = np.stack(c2w)
    c2w4 = np.tile(np.eye(4), (len(c2w), 1, 1))
    c2w4[:, :3, :4] = c2w
    c2w4 = c2w4 @ _GL_TO_CV
    viewmats = _viewmats_from_c2w(c2w4[:, :3, :4])
    names = [str(p.relative_to(root)) for p in paths]
    cams = Cameras(viewmats.float(), Ks.float(), imgs.shape[2], imgs.shape[1], names)
    # no point cloud: random points in a cube around the point the cameras look at
    centre = focus_point(cams)
    radius = float((cams.centers.double().cpu() - centre).norm(dim=1).mean())
    half = radius / 3.0
    g = torch.Generator().manual_seed(seed)
    xyz = centre.float() + (torch.rand(num_random_points, 3, generator=g) * 2 - 1) * half
    rgb = torch.rand(num_random_points, 3, generator=g)
    near, far = max(radius - half * 3 ** 0.5, 1e-3 * radius), radius + half * 3 ** 0.5
    test_mask = is_test if any(is_test) else None
    return dict(cameras=cams, images=imgs, names=names, points=(xyz, rgb), points_source="random", near=near,
                far=far, image_dir=str(Path(names[0]).parent), undistortion=undist, test_mask=test_mask)


_LOADERS = {"colmap": _load_colmap, "llff": _load_llff, "transforms": _load_transforms}


def load_dataset(path: str | Path, images: str = "images", split_every: int = 8,
                 background: Sequence[float] = (1.0, 1.0, 1.0), max_images: Optional[int] = None,
                 device=None, *, width: Optional[int] = None, num_random_points: int = 100_000,
                 seed: int = 0, format: Optional[str] = None) -> SceneData:
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
    """
    root = _as_path(path)
    fmt = format or detect_format(root)
    if fmt not in _LOADERS:
        raise InputError(f"unknown data format '{fmt}' (colmap, llff or transforms)")
    if split_every is None or split_every < 0:
        raise InputError(f"split_every must be >= 0, got {split_every}")
    bg = tuple(float(v) for v in background)
    if len(bg) != 3:
        raise InputError(f"background must be 3 numbers (RGB), got {background!r}")
    d = _LOADERS[fmt](root, images=images, max_images=max_images, width=width, background=bg,
                      num_random_points=int(num_random_points), seed=seed)
    test_mask = d.pop("test_mask", None)
    train, test = _split(len(d["names"]), split_every, test_mask)
    options = dict(images=images, split_every=split_every, background=list(bg), max_images=max_images,
                   width=width, num_random_points=int(num_random_points), seed=seed, format=fmt)
    data = SceneData(train_ids=train, test_ids=test, background=bg, data_dir=root.resolve(), format=fmt,
                     options=options, **d)
    log.info("loaded %s capture %s: %d images %dx%d (%d train, %d test), %s points", fmt, root, len(data),
             data.width, data.height, len(train), len(test),
             "no" if data.points is None else f"{len(data.points[0])} {data.points_source}")
    return data.to(device) if device is not None else data


# ----------------------------------------------------------------------------- runs
def data_json(data: SceneData, **extra) -> dict:
    """The ``data.json`` record of a run trained on ``data``."""
    return {
        "data_dir": str(data.data_dir) if data.data_dir is not None else None,
        "format": data.format,
        "images": data.options.get("images", data.image_dir),
        "width": data.width,
        "height": data.height,
        "split": {"train": [data.names[i] for i in data.train_ids], "test": [data.names[i] for i in data.test_ids]},
        "background": list(data.background),
        "undistorted": data.undistorted,
        "undistortion": data.undistortion,
        "near": data.near,
        "far": data.far,
        "points_source": data.points_source,
        "load_options": data.options,
        **extra,
    }


def load_run(scene_dir: str | Path, device=None, *, data_dir: Optional[str | Path] = None,
             load_images: bool = True):
    """Read a reconstruction run: ``(GaussianScene, SceneData)``.

    The scene comes from ``scene.ply``, the cameras from ``cameras.json`` (training
    resolution) and the split and data options from ``data.json``; the images are
    reloaded from the capture (``data_dir`` overrides the recorded folder, e.g. after
    moving it). With ``load_images=False`` the images are left black (cameras only).
    """
    from .fileio import read_json
    from .ply import read_ply

    scene_dir = _as_path(scene_dir)
    if not scene_dir.is_dir():
        raise InputError(f"{scene_dir}: run folder not found")
    for f in ("scene.ply", "cameras.json", "data.json"):
        if not (scene_dir / f).is_file():
            raise InputError(f"{scene_dir}: not a reconstruction run (no {f}); run `ssgwarp reconstruct` first")
    scene = read_ply(scene_dir / "scene.ply")
    cams = Cameras.load(scene_dir / "cameras.json")
    meta = read_json(scene_dir / "data.json")
    if not isinstance(meta, dict) or "split" not in meta:
        raise InputError(f"{scene_dir / 'data.json'}: unexpected layout (no 'split')")
    split = meta["split"]
    index = {n: i for i, n in enumerate(cams.names)}
    unknown = [n for n in list(split.get("train", [])) + list(split.get("test", [])) if n not in index]
    if unknown:
        raise InputError(f"{scene_dir / 'data.json'}: split names not in cameras.json: {', '.join(unknown[:5])}")
    train = [index[n] for n in split.get("train", [])]
    test = [index[n] for n in split.get("test", [])]
    bg = tuple(float(v) for v in meta.get("background", (1.0, 1.0, 1.0)))
    src = data_dir or meta.get("data_dir")
    points = None
    images = torch.zeros(len(cams), cams.height, cams.width, 3)
    data_root = _as_path(src) if src else None
    undistortion = meta.get("undistortion")
    if load_images:
        if data_root is None or not data_root.is_dir():
            raise InputError(f"{scene_dir / 'data.json'}: capture folder {src} not found "
                             f"(pass data_dir= / --data-dir to say where it is now)")
        opts = dict(meta.get("load_options", {}))
        opts.pop("split_every", None)
        opts["width"] = cams.width
        data = load_dataset(data_root, **{k: opts[k] for k in ("images", "background", "width", "max_images",
                                                                 "num_random_points", "seed", "format")
                                         if k in opts})
        pos = {n: i for i, n in enumerate(data.names)}
        missing = [n for n in cams.names if n not in pos]
        if missing:
            raise _missing_error(missing, data_root, f"{scene_dir / 'cameras.json'}")
        sel = [pos[n] for n in cams.names]
        images = data.images[sel]
        if (data.width, data.height) != (cams.width, cams.height) or not torch.allclose(
                data.cameras.Ks[sel].double(), cams.Ks.double(), rtol=0.0, atol=1e-2):
            raise InputError(f"{data_root} now loads as {data.width}x{data.height} images with other intrinsics "
                             f"than the run's {scene_dir / 'cameras.json'} ({cams.width}x{cams.height}): the run was "
                             f"made from other data or by an ssgwarp that did not crop undistorted images; run "
                             f"`ssgwarp reconstruct` again")
        points, undistortion = data.points, data.undistortion
    out = SceneData(cameras=cams, images=images, names=list(cams.names), train_ids=train, test_ids=test,
                    points=points, points_source=meta.get("points_source", "none"), near=meta.get("near"),
                    far=meta.get("far"), background=bg, data_dir=data_root, image_dir=meta.get("images"),
                    format=meta.get("format", ""), undistortion=undistortion, options=meta.get("load_options", {}))
    if device is not None:
        scene, out = scene.to(device), out.to(device)
    return scene, out
