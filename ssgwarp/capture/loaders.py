"""The readers of the three capture layouts (:mod:`ssgwarp.capture.datasets` documents them and picks
one): COLMAP models, LLFF ``poses_bounds.npy``, NeRF / instant-ngp ``transforms*.json``. Each
returns the pieces of a :class:`~ssgwarp.capture.datasets.SceneData` as a dict (cameras, images, names,
points, near / far, undistortion record); the shared image handling (finding, loading,
compositing, undistorting and resizing images) and the point / camera helpers live here too.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from ..core.progress import tqdm

from ..core.cameras import Cameras
from ..formats.colmap import _pick, find_model, read_cameras, read_model, read_points3d
from ..errors import InputError
from ..core.fileio import read_image, read_json
from .lens import Lens, plan_undistortion
from ..formats.ply import read_points

log = logging.getLogger("ssgwarp.capture.datasets")

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff", ".bmp", ".webp", ".PNG", ".JPG", ".JPEG")
# OpenGL camera axes (x right, y up, z back) -> OpenCV (x right, y down, z forward)
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _lens(cam) -> Optional[Lens]:
    """A COLMAP camera's distortion as a :class:`Lens` (None for the pinhole models)."""
    d = cam.distortion
    return None if d is None else Lens(*d)


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


def missing_images_error(missing: Sequence[str], folder: Path, source: str) -> InputError:
    shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
    return InputError(f"{len(missing)} image(s) referenced by {source} are missing from {folder}: {shown}")


def _evenly(n: int, k: Optional[int]) -> list[int]:
    if k is None or k >= n:
        return list(range(n))
    if k <= 0:
        raise InputError(f"max_images must be positive, got {k}")
    return sorted(set(np.linspace(0, n - 1, k).round().astype(int).tolist()))


def _load_images(paths: Sequence[Path], background, width: Optional[int],
                 intrinsics: Callable, mask_paths: Optional[Sequence[Path]] = None, progress: bool = True
                 ) -> tuple[torch.Tensor, torch.Tensor, Optional[dict]]:
    """Read, composite RGBA, remove lens distortion and resize, one image at a time.

    ``intrinsics(w0, h0)`` gives, for files of ``w0`` x ``h0`` pixels, ``(Ks [C, 3, 3] float64,
    lenses [C] (:class:`~ssgwarp.capture.lens.Lens` or None), labels [C] (each image's camera, for errors))``.
    Distorted images become the pinhole crop of :func:`ssgwarp.capture.lens.plan_undistortion` (at the files'
    resolution, before any resize). ``mask_paths``: one mask image per image (its first channel, > 0: keep),
    undistorted and resized with it as a 4th channel of the returned images. Returns ``(images [C, H, W, 3], Ks [C, 3, 3] float64 of those
    images, the undistortion record or None)``.
    """


    if width is not None and width <= 0:
        raise InputError(f"width must be positive, got {width}")
    out = []
    size0 = plan = Ks = None
    h = w = hu = wu = 0
    bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
    it = tqdm(paths, desc="loading images", unit="img", leave=False, disable=not progress or len(paths) < 16)
    for i, p in enumerate(it):
        img = read_image(p)
        if img.shape[2] == 1 or img.shape[2] == 2:
            img = np.concatenate([np.repeat(img[..., :1], 3, axis=2), img[..., 1:]], axis=2)
        if img.shape[2] >= 4:
            # OpenImageIO hands back associated (premultiplied) alpha: over-composite is rgb + (1 - a) * bg
            a = np.clip(img[..., 3:4], 0.0, 1.0)
            img = img[..., :3] + (1.0 - a) * bg
        img = np.clip(img[..., :3], 0.0, 1.0)
        if mask_paths is not None:
            m = read_image(mask_paths[i])
            if m.shape[:2] != img.shape[:2]:
                raise InputError(f"{mask_paths[i]}: mask size {m.shape[1]}x{m.shape[0]} differs from its image's "
                                 f"({img.shape[1]}x{img.shape[0]})")
            img = np.concatenate([img, (m[..., :1] > 0).astype(np.float32)], axis=2)
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
            if getattr(width, "at_most", False) and width >= wu:
                width = None              # (a preset's width: never wider than the capture)
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


def _viewmats_from_c2w(c2w: np.ndarray) -> torch.Tensor:
    c2w = np.asarray(c2w, dtype=np.float64)
    m = np.tile(np.eye(4), (c2w.shape[0], 1, 1))
    m[:, :3, :4] = c2w[:, :3, :4]
    if not np.all(np.isfinite(m)):
        raise InputError("camera poses contain NaN/inf values")
    det = np.linalg.det(m[:, :3, :3])
    if not (np.abs(det) > 1e-12).all():
        raise InputError(f"camera pose {int(np.argmax(~(np.abs(det) > 1e-12)))} has a singular rotation "
                         f"(determinant {det[np.argmax(~(np.abs(det) > 1e-12))]:.3g})")
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
                            n: int, seed: int = 0, log_depth=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points at random pixels of random views, at depths uniform in disparity between each
    view's ``near`` and ``far`` (uniform in log depth for the views where ``log_depth``, a per-view bool array,
    is set); coloured by that pixel. Returns ``(xyz [n,3], rgb [n,3])``."""
    g = torch.Generator().manual_seed(seed)
    c = len(cameras)
    cam = torch.randint(0, c, (n,), generator=g)
    u = torch.rand(n, generator=g, dtype=torch.float64) * cameras.width
    v = torch.rand(n, generator=g, dtype=torch.float64) * cameras.height
    near_t = torch.as_tensor(near, dtype=torch.float64)[cam]
    far_t = torch.as_tensor(far, dtype=torch.float64)[cam]
    t = torch.rand(n, generator=g, dtype=torch.float64)
    depth = 1.0 / (1.0 / near_t * (1 - t) + 1.0 / far_t * t)
    if log_depth is not None:
        log = torch.as_tensor(np.asarray(log_depth, dtype=bool))[cam]
        depth = torch.where(log, near_t * (far_t / near_t) ** t, depth)
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
def _load_colmap(root: Path, images: str, max_images, width, background, progress=True, **_):
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
        raise missing_images_error(missing, folder, f"{model.path}/images")
    cam_of = [model.cameras[im.camera_id] for im in ims]
    cam_file = next((p for p in (model.path / "cameras.bin", model.path / "cameras.txt") if p.is_file()), model.path)

    def intrinsics(w0, h0):
        Ks = []
        for cam in cam_of:
            K = cam.K.copy()
            K[0] *= w0 / cam.width
            K[1] *= h0 / cam.height
            Ks.append(K)
        return np.stack(Ks), [_lens(c) for c in cam_of], [f"{cam_file}: camera {c.id}" for c in cam_of]

    imgs, Ks, undist = _load_images(paths, background, width, intrinsics, progress=progress)
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


def read_poses_bounds(path: Path) -> np.ndarray:
    """LLFF's ``poses_bounds.npy`` as float64 ``[N, 17]``, checked: an ``.npy`` of numbers of that shape whose
    size is what its header says (read without trusting a count: a damaged header cannot make it allocate
    more than the file holds), finite, with positive image size, focal length and near/far bounds and an
    invertible rotation per pose. Anything else raises :class:`InputError` naming ``path``."""
    path = Path(path)
    shape_msg = "(LLFF expects [N, 17]: 3x5 pose-and-hwf + near/far per image)"
    try:
        with open(path, "rb") as f:
            size = path.stat().st_size
            version = np.lib.format.read_magic(f)
            if version not in ((1, 0), (2, 0), (3, 0)):
                raise ValueError(f"unknown .npy version {version}")
            start = f.tell()
            n_len = 2 if version == (1, 0) else 4
            hlen = int.from_bytes(f.read(n_len), "little")
            if start + n_len + hlen > size or hlen > 65535:      # (read() would reserve what the field says)
                raise ValueError(f"its header length {hlen} runs past the end of the file")
            f.seek(start)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(f)
            body = f.read()
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None
    except Exception as e:          # numpy's header parser: ValueError, SyntaxError, ...
        raise InputError(f"{path}: cannot read (not a valid .npy file: {str(e).splitlines()[0] if str(e) else type(e).__name__})"
                         ) from None
    if dtype.kind not in "fiu" or dtype.hasobject:
        raise InputError(f"{path}: holds {dtype} values, not numbers {shape_msg}")
    if len(shape) != 2 or shape[1] != 17 or shape[0] == 0:
        raise InputError(f"{path}: poses of the wrong shape {tuple(shape)} {shape_msg}")
    if shape[0] * 17 * dtype.itemsize != len(body):
        raise InputError(f"{path}: truncated or corrupt (its header says {shape[0]}x17 {dtype} values, "
                         f"{shape[0] * 17 * dtype.itemsize} bytes; the file holds {len(body)})")
    pb = np.frombuffer(body, dtype=dtype).reshape(shape, order="F" if fortran else "C").astype(np.float64)
    if not np.all(np.isfinite(pb)):
        raise InputError(f"{path}: contains NaN/inf values")
    hwf, bounds = pb[:, :15].reshape(-1, 3, 5)[:, :, 4], pb[:, 15:17]
    if not (hwf > 0).all():
        i = int(np.argmax(~(hwf > 0).all(axis=1)))
        raise InputError(f"{path}: pose {i} has image size / focal length {hwf[i].tolist()} (all must be positive)")
    if not (bounds > 0).all():
        i = int(np.argmax(~(bounds > 0).all(axis=1)))
        raise InputError(f"{path}: pose {i} has near/far bounds {bounds[i].tolist()} (both must be positive)")
    det = np.linalg.det(pb[:, :15].reshape(-1, 3, 5)[:, :, :3])
    if not (np.abs(det) > 1e-6).all():
        i = int(np.argmax(~(np.abs(det) > 1e-6)))
        raise InputError(f"{path}: pose {i} has a singular rotation (determinant {det[i]:.3g})")
    return pb


def _load_llff(root: Path, images: str, max_images, width, background, num_random_points, seed, progress=True, **_):
    pb_path = root / "poses_bounds.npy"
    pb = read_poses_bounds(pb_path)
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
                    lens, label = _lens(cc), f"{pb_path} with the lens of {cam_file}: camera {cc.id}"
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

    imgs, Ks, undist = _load_images([folder / f for f in files], background, width, intrinsics,
                                     progress=progress)
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
    err = np.seterr(all="ignore")      # (an angle of inf or pi: checked below, no warning)
    try:
        if "fl_x" in meta or "fl_y" in meta:
            fx = float(meta.get("fl_x", meta.get("fl_y")))
            fy = float(meta.get("fl_y", fx))
        elif "camera_angle_x" in meta:
            fx = 0.5 * w / np.tan(0.5 * float(meta["camera_angle_x"]))
            fy = 0.5 * h / np.tan(0.5 * float(meta["camera_angle_y"])) if "camera_angle_y" in meta else fx
        cx = float(meta.get("cx", w / 2.0))
        cy = float(meta.get("cy", h / 2.0))
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{where}: intrinsics are not numbers") from None
    finally:
        np.seterr(**err)
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        raise InputError(f"{where}: invalid intrinsics fx={fx} fy={fy}")
    return fx, fy, cx, cy


_TRANSFORMS_MODELS = ("OPENCV", "OPENCV_FISHEYE", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
# nerfstudio's models that are not a pinhole with a radial-tangential or fisheye lens
_PANORAMIC_MODELS = ("EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")


def _transforms_lens(meta: dict, where: str):
    """The lens of a transforms.json camera: ``k1 k2 k3 p1 p2`` (OpenCV, k3 the r^6 term), or with
    instant-ngp's ``is_fisheye`` / nerfstudio's ``camera_model: OPENCV_FISHEYE`` the fisheye ``k1..k4``."""
    model = str(meta.get("camera_model", "")).upper()
    if model in _PANORAMIC_MODELS:
        raise InputError(f"{where}: camera_model {meta['camera_model']} (a panorama) is not supported: ssgwarp "
                         f"trains on perspective images; cut the panoramas into perspective views first")
    if model and model not in _TRANSFORMS_MODELS:
        raise InputError(f"{where}: camera_model {meta['camera_model']} is not supported (supported: "
                         f"{', '.join(_TRANSFORMS_MODELS)}); convert the capture to pinhole images first")
    flag = meta.get("is_fisheye", False)
    fisheye = model == "OPENCV_FISHEYE" or (flag.strip().lower() in ("1", "true") if isinstance(flag, str)
                                            else bool(flag))
    try:
        k1, k2, k3, k4, p1, p2 = (float(meta.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    except (TypeError, ValueError, OverflowError):
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


def _applied_transform(meta: dict, where: str) -> Optional[list]:
    """nerfstudio's ``applied_transform`` (3x4 or 4x4, the map from the original COLMAP world to the frames' world),
    checked, as a 3x4 list; None when absent."""
    if "applied_transform" not in meta:
        return None
    try:
        m = np.asarray(meta["applied_transform"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        m = np.zeros(0)
    if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
        raise InputError(f"{where}: applied_transform must be a 3x4 matrix of numbers")
    return m[:3, :4].tolist()


def _frame_path(value, jpath: Path, i: int, key: str) -> str:
    if not isinstance(value, str) or not value.strip() or "\x00" in value:
        raise InputError(f"{jpath}: frame {i}: {key} must be a file name (got {str(value)[:60]!r})")
    return value


def _json_size(meta: dict, key: str, default: int, where: str) -> int:
    """``meta[key]`` (``w``/``h``, the size the JSON's intrinsics are given at) as a positive integer."""
    if key not in meta:
        return default
    v = meta[key]
    if isinstance(v, str):               # ("64": some writers quote their numbers)
        try:
            v = float(v)
        except ValueError:
            pass
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1 << 20 or v != int(v):
        raise InputError(f"{where}: '{key}' must be a positive whole number of pixels (got {str(v)[:40]})")
    return int(v)


def read_transforms(root: Path, images: str = "images") -> list[dict]:
    """The frames of a NeRF / instant-ngp / nerfstudio capture (``transforms.json``, or
    ``transforms_train.json`` + ``transforms_test.json``), read and checked before any image is: per frame
    ``jpath`` (its JSON), ``meta`` (that JSON's top level), ``merged`` (top level + the frame's own keys),
    ``rel`` (its image path; a leading ``images/`` becomes ``images``), ``mask`` (``mask_path`` or None),
    ``c2w`` (3x4 float64, OpenGL axes), ``lens``, ``test`` (from transforms_test.json). Intrinsics, sizes,
    lens, ``applied_transform`` and poses are checked here (non-numbers, NaN/inf, wrong shapes, singular
    rotations: :class:`InputError` naming the file and the frame)."""
    if (root / "transforms.json").is_file():
        sources = [(root / "transforms.json", False)]
    else:
        sources = [(root / "transforms_train.json", False)]
        if (root / "transforms_test.json").is_file():
            sources.append((root / "transforms_test.json", True))
    out = []
    for jpath, test in sources:
        meta = read_json(jpath)
        if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
            raise InputError(f"{jpath}: expected an object with a non-empty 'frames' list")
        _applied_transform(meta, str(jpath))
        for i, fr in enumerate(meta["frames"]):
            if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
                raise InputError(f"{jpath}: frame {i} needs 'file_path' and 'transform_matrix'")
            rel = Path(_frame_path(fr["file_path"], jpath, i, "file_path"))
            if images != "images" and rel.parts and rel.parts[0] == "images":
                rel = Path(images, *rel.parts[1:])
            mask = _frame_path(fr["mask_path"], jpath, i, "mask_path") if "mask_path" in fr else None
            try:
                m = np.asarray(fr["transform_matrix"], dtype=np.float64)
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"{jpath}: transform_matrix of {rel} is not a matrix of numbers") from None
            if m.shape not in ((4, 4), (3, 4)):
                raise InputError(f"{jpath}: transform_matrix of {rel} has the wrong shape {m.shape} (expected 4x4)")
            if not np.isfinite(m).all():
                raise InputError(f"{jpath}: transform_matrix of {rel} holds NaN/inf values")
            if not abs(np.linalg.det(m[:3, :3])) > 1e-12:
                raise InputError(f"{jpath}: transform_matrix of {rel} has a singular rotation")
            merged = {**meta, **{k: v for k, v in fr.items() if k not in ("file_path", "transform_matrix")}}
            where = f"{jpath}: frame {rel}"
            jw, jh = _json_size(merged, "w", 64, where), _json_size(merged, "h", 64, where)
            _intrinsics_from(merged, jw, jh, where)          # (checked now, at any size: again at the images')
            out.append(dict(jpath=jpath, meta=meta, merged=merged, rel=rel, mask=mask, c2w=m[:3, :4],
                            lens=_transforms_lens(merged, where), test=test, where=where))
    return out


def _load_transforms(root: Path, images: str, max_images, width, background, num_random_points, seed, progress=True,
                     **_):
    frames = read_transforms(root, images)
    frames = [frames[i] for i in _evenly(len(frames), max_images)]
    metas = [(f["jpath"], f["meta"]) for f in frames]
    is_test = [f["test"] for f in frames]
    paths, missing = [], []
    for fr in frames:
        p = _resolve_image(root, str(fr["rel"]))
        (missing.append(str(fr["rel"])) if p is None else paths.append(p))
    if missing:
        raise missing_images_error(missing, root, ", ".join(sorted({m[0].name for m in metas})))
    c2w = [fr["c2w"] for fr in frames]
    # nerfstudio masks (``mask_path`` per frame: 0 = not part of the scene): all frames or none
    with_mask = [fr["mask"] is not None for fr in frames]
    mask_paths = None
    if any(with_mask):
        if not all(with_mask):
            raise InputError(f"{metas[0][0]}: mask_path is given for {sum(with_mask)} of {len(frames)} frames; "
                             f"give it for every frame or none")
        mask_paths, missing = [], []
        for fr in frames:
            q = _resolve_image(root, fr["mask"])
            (missing.append(fr["mask"]) if q is None else mask_paths.append(q))
        if missing:
            raise missing_images_error(missing, root, f"{metas[0][0].name} (mask_path)")
    cams_meta = [(fr["merged"], f"{fr['jpath']}: frame {p.relative_to(root)}", fr["lens"])
                 for fr, p in zip(frames, paths)]

    def intrinsics(w0, h0):
        Ks = []
        for merged, where, _ in cams_meta:
            jw, jh = _json_size(merged, "w", w0, where), _json_size(merged, "h", h0, where)
            fx, fy, cx, cy = _intrinsics_from(merged, jw, jh, where)
            sx, sy = w0 / jw, h0 / jh
            Ks.append([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])
        return np.array(Ks), [c[2] for c in cams_meta], [c[1] for c in cams_meta]

    imgs, Ks, undist = _load_images(paths, background, width, intrinsics, mask_paths, progress=progress)
    masks = None
    if mask_paths is not None:  # (the masks travel as a 4th channel through undistortion and resizing)
        imgs, masks = imgs[..., :3].contiguous(), (imgs[..., 3] >= 0.5).float()
    c2w = np.stack(c2w)
    c2w4 = np.tile(np.eye(4), (len(c2w), 1, 1))
    c2w4[:, :3, :4] = c2w
    c2w4 = c2w4 @ _GL_TO_CV
    viewmats = _viewmats_from_c2w(c2w4[:, :3, :4])
    names = [str(p.relative_to(root)) for p in paths]
    cams = Cameras(viewmats.float(), Ks.float(), imgs.shape[2], imgs.shape[1], names)
    top = metas[0][1]
    applied = _applied_transform(top, str(metas[0][0]))
    test_mask = is_test if any(is_test) else None
    extra = dict(test_mask=test_mask, masks=masks, applied_transform=applied)
    if top.get("ply_file_path"):
        # nerfstudio's sparse_pc.ply: ns-process-data writes COLMAP's points with applied_transform already
        # applied, i.e. in the frames' world (the one transform_matrix is in): used as they are
        xyz, rgb = read_points(root / str(top["ply_file_path"]))
        near, far = _depth_range(xyz.double().numpy(), viewmats.numpy())
        return dict(cameras=cams, images=imgs, names=names, points=(xyz, rgb), points_source="ply", near=near, far=far,
                    image_dir=str(Path(names[0]).parent), undistortion=undist, **extra)
    # no point cloud: random points in a cube around the point the cameras look at
    centre = focus_point(cams)
    radius = float((cams.centers.double().cpu() - centre).norm(dim=1).mean())
    half = radius / 3.0
    g = torch.Generator().manual_seed(seed)
    xyz = centre.float() + (torch.rand(num_random_points, 3, generator=g) * 2 - 1) * half
    rgb = torch.rand(num_random_points, 3, generator=g)
    near, far = max(radius - half * 3 ** 0.5, 1e-3 * radius), radius + half * 3 ** 0.5
    return dict(cameras=cams, images=imgs, names=names, points=(xyz, rgb), points_source="random", near=near,
                far=far, image_dir=str(Path(names[0]).parent), undistortion=undist, **extra)


LOADERS = {"colmap": _load_colmap, "llff": _load_llff, "transforms": _load_transforms}
