"""Splats trained by other tools: their files, and the frames they are in.

Readers (each returns our :class:`~ssgwarp.raster.scene.GaussianScene`, parameters as stored:
log scales, logit opacities, wxyz quaternions, SH DC + higher bands):

* graphdeco 3DGS output folders (:func:`graphdeco_folder`): ``point_cloud/iteration_N/point_cloud.ply``
  (the INRIA PLY layout, :mod:`ssgwarp.formats.ply`), ``cameras.json`` (per view ``id``, ``img_name``,
  ``width``, ``height``, ``position`` (camera centre), ``rotation`` (camera-to-world 3x3, OpenCV
  axes), ``fx``, ``fy``; principal point at the image centre: :func:`graphdeco_cameras`) and
  ``cfg_args`` (the training options as Python's ``Namespace(...)`` text: :func:`parse_cfg_args`);
* gsplat ``simple_trainer`` checkpoints (:func:`read_gsplat_checkpoint`): ``{"step", "splats":
  {means, quats, scales, opacities, sh0 [N,1,3], shN [N,K,3]}}``; its PLY export is the INRIA layout
  without normals;
* nerfstudio ``dataparser_transforms.json`` (:func:`nerfstudio_to_capture`): ``transform`` (3x4) and
  ``scale`` map the capture's original frame to the frame splatfacto trained in (and ``ns-export
  gaussian-splat`` writes), ``x_dp = scale * (transform @ [x; 1])``; a ``transforms.json`` with an
  ``applied_transform`` (3x4) holds the cameras in ``applied_transform @ [x; 1]``.

Frames (the geometry is :mod:`ssgwarp.core.frames`): :func:`transform_scene` moves a scene by a
:class:`~ssgwarp.core.frames.Similarity` exactly: means, rotations (``q_R * q``), log scales
(``+ log s``) and the SH bands (:func:`~ssgwarp.core.frames.rotate_sh`). :func:`gsplat_normalization`
recomputes the similarity with which gsplat's COLMAP parser normalises the world
(``normalize_world_space``, its default), as the candidates that differ only in the signs of the
principal axes.
"""
from __future__ import annotations

import ast
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..core.cameras import Cameras
from ..core.fileio import read_json
from ..core.frames import Similarity, quat_mul, rotate_sh
from ..core.geometry import rotmat_to_quat
from ..errors import InputError
from ..raster.scene import GaussianScene

__all__ = ["transform_scene", "gsplat_normalization", "read_gsplat_checkpoint", "gsplat_checkpoints",
           "graphdeco_folder", "graphdeco_cameras", "parse_cfg_args", "nerfstudio_to_capture", "GraphdecoOutput",
           "match_names"]


def transform_scene(scene: GaussianScene, sim: Similarity) -> GaussianScene:
    """``scene`` moved by ``sim``: renders from :meth:`Similarity.cameras` equal the old ones from the
    old cameras (up to rounding). Computed in float64, returned in the scene's dtype."""
    if sim.is_identity:
        return scene
    dt = scene.dtype
    s = scene.to(dtype=torch.float64)
    R = torch.from_numpy(sim.R).to(s.device)
    means = sim.scale * s.means @ R.T + torch.from_numpy(sim.t).to(s.device)
    qR = rotmat_to_quat(R)
    quats = quat_mul(qR.expand_as(s.quats), s.quats)
    log_scales = s.log_scales + math.log(sim.scale)
    rest = None if s.sh_rest is None else rotate_sh(s.sh_rest, sim.R, s.sh_degree)
    return s.replace(means=means, quats=quats, log_scales=log_scales, sh_rest=rest).to(dtype=dt)


# ----------------------------------------------------------------------------- gsplat's world normalisation
def _up_and_centre(c2w: np.ndarray) -> np.ndarray:
    """gsplat's first step (after nerf-factory): rotate the mean camera up (-y) onto +z, move the
    median of the points nearest the origin on the optical axes to the origin, scale the median
    camera distance to 1. Returns the 4x4 similarity."""
    R, t = c2w[:, :3, :3], c2w[:, :3, 3]
    up = -R[:, :, 1].mean(0)
    up /= np.linalg.norm(up)
    target = np.array([0.0, -1.0, 0.0])   # (gsplat rotates the world up onto the camera's up -y axis)
    c = float(up @ target)
    k = np.cross(up, target)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    Ra = np.eye(3) + K + K @ K / (1.0 + c) if c > -1 else np.diag([-1.0, 1.0, 1.0])
    R2, t2 = Ra @ R, t @ Ra.T
    fwd = R2[:, :, 2]
    nearest = t2 - (fwd * t2).sum(-1, keepdims=True) * fwd
    shift = -np.median(nearest, axis=0)
    scale = 1.0 / np.median(np.linalg.norm(t2 + shift, axis=-1))
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = Ra, shift
    m[:3, :] *= scale
    return m


def gsplat_normalization(c2w: np.ndarray, points: np.ndarray) -> list[tuple[str, Similarity]]:
    """The frames gsplat's COLMAP parser may have trained in (``normalize_world_space``): the
    camera step of :func:`_up_and_centre`, then the points' principal axes (largest variance first,
    around their median) as the new x, y, z, then z flipped when the median point is above the mean.

    The principal axes' signs depend on the eigen-solver, so every proper choice of signs is a
    candidate: four ``(label, Similarity)`` from capture to gsplat frame, the one gsplat's own rule
    gives with numpy's solver first. ``c2w [C, 4, 4]`` (OpenCV axes) and ``points [P, 3]`` are the
    COLMAP model's (points as float32, as gsplat reads them)."""
    if points is None or len(points) < 3:
        raise InputError("gsplat's world normalisation needs the COLMAP model's points3D (3 or more points)")
    T1 = _up_and_centre(np.asarray(c2w, np.float64))
    p = np.asarray(points, np.float32).astype(np.float64) @ T1[:3, :3].T + T1[:3, 3]
    centre = np.median(p, axis=0)
    w, V = np.linalg.eigh(np.cov(p - centre, rowvar=False))
    V = V[:, np.argsort(w)[::-1]]
    if np.linalg.det(V) < 0:
        V[:, 0] *= -1
    signs = [(1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)]
    z = (p - centre) @ V[:, 2]
    if np.median(z) > np.mean(z):     # gsplat's rule: z flipped (about x) when the median point is above the mean
        signs[0], signs[1] = signs[1], signs[0]
    out = []
    for sg in signs:
        Rp = np.diag(np.array(sg, np.float64)) @ V.T
        T2 = np.eye(4)
        T2[:3, :3], T2[:3, 3] = Rp, -Rp @ centre
        out.append((f"gsplat's normalised world (principal axes x{sg[0]:+d} y{sg[1]:+d} z{sg[2]:+d})",
                    Similarity.from_matrix(T2 @ T1)))
    return out


# ----------------------------------------------------------------------------- gsplat checkpoints
_CKPT = re.compile(r"ckpt_(\d+)(?:_rank(\d+))?\.pt$")


def gsplat_checkpoints(folder: Path) -> dict[int, Path]:
    """``{step: path}`` of a gsplat result folder's ``ckpts/ckpt_STEP_rankR.pt`` (rank 0, or unranked)."""
    out: dict[int, Path] = {}
    for p in sorted((folder / "ckpts").glob("ckpt_*.pt")) if (folder / "ckpts").is_dir() else []:
        m = _CKPT.search(p.name)
        if m and int(m.group(2) or 0) == 0:
            out[int(m.group(1))] = p
    return out


def read_gsplat_checkpoint(path: str | Path) -> tuple[GaussianScene, Optional[int]]:
    """``(scene, step)`` of a gsplat ``simple_trainer`` checkpoint (``splats``: means [N,3], quats
    [N,4] wxyz, scales [N,3] log, opacities [N] logit, sh0 [N,1,3], shN [N,K,3])."""
    path = Path(path)
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(f"{path}: not a readable PyTorch checkpoint ({str(e).splitlines()[0] if str(e) else e})") \
            from None
    sp = ck.get("splats") if isinstance(ck, dict) else None
    if not isinstance(sp, dict):
        raise InputError(f"{path}: no 'splats' dict (expected a gsplat simple_trainer checkpoint)")
    need = ("means", "quats", "scales", "opacities")
    missing = [k for k in need if k not in sp]
    if missing:
        raise InputError(f"{path}: splats lack {', '.join(missing)}")
    if "sh0" not in sp:
        raise InputError(f"{path}: splats hold {', '.join(sorted(sp))} but no sh0 (an appearance-optimised "
                         f"model, --app_opt, has no SH colours: export it with gsplat's --save_ply and import the PLY)")
    f = {k: torch.as_tensor(v).detach().float() for k, v in sp.items()}
    n = f["means"].shape[0]
    sh0 = f["sh0"].reshape(n, 3)
    shN = f.get("shN")
    k = 0 if shN is None else int(shN.shape[1])
    degrees = {(d + 1) ** 2 - 1: d for d in range(4)}
    if k not in degrees:
        raise InputError(f"{path}: shN has {k} bands per colour, which matches no SH degree 0..3")
    deg = degrees[k]
    try:
        scene = GaussianScene(f["means"], f["scales"], f["quats"], f["opacities"].reshape(n), sh0,
                              shN.reshape(n, k, 3) if deg else None, None, deg)
    except (InputError, RuntimeError) as e:
        raise InputError(f"{path}: {e}") from None
    for name, t in scene.tensors().items():
        if not torch.isfinite(t).all():
            raise InputError(f"{path}: {name} holds NaN/inf values")
    step = ck.get("step")
    return scene, (int(step) if isinstance(step, (int, np.integer)) or (torch.is_tensor(step)) else None)


# ----------------------------------------------------------------------------- graphdeco 3DGS
@dataclass
class GraphdecoOutput:
    """A graphdeco 3DGS output folder: the PLY of the chosen iteration, its camera records, options."""

    ply: Path
    iteration: int
    cameras: Optional[list]       # cameras.json's entries (None when absent)
    cfg: dict                     # cfg_args (empty when absent)


def parse_cfg_args(text: str, where: str = "cfg_args") -> dict:
    """The options of a graphdeco ``cfg_args`` file (``Namespace(key=value, ...)``; values literal)."""
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except SyntaxError:
        raise InputError(f"{where}: not a Namespace(...) record") from None
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "Namespace"):
        raise InputError(f"{where}: not a Namespace(...) record")
    out = {}
    for kw in node.keywords:
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except ValueError:
            out[kw.arg] = None
    return out


def graphdeco_folder(folder: str | Path, iteration: Optional[int] = None) -> GraphdecoOutput:
    folder = Path(folder)
    its = {}
    for p in (folder / "point_cloud").glob("iteration_*/point_cloud.ply"):
        m = re.fullmatch(r"iteration_(\d+)", p.parent.name)
        if m:
            its[int(m.group(1))] = p
    if not its:
        raise InputError(f"{folder}: no point_cloud/iteration_N/point_cloud.ply (not a graphdeco 3DGS output)")
    if iteration is None:
        iteration = max(its)
    elif iteration not in its:
        raise InputError(f"{folder}: no iteration {iteration} (it holds {', '.join(map(str, sorted(its)))})")
    cams = None
    if (folder / "cameras.json").is_file():
        cams = read_json(folder / "cameras.json")
        if not isinstance(cams, list) or not cams:
            raise InputError(f"{folder / 'cameras.json'}: expected a non-empty list of cameras")
    cfg = parse_cfg_args((folder / "cfg_args").read_text(), str(folder / "cfg_args")) \
        if (folder / "cfg_args").is_file() else {}
    return GraphdecoOutput(its[iteration], iteration, cams, cfg)


def graphdeco_cameras(entries: list, where: str = "cameras.json") -> Cameras:
    """:class:`Cameras` of graphdeco ``cameras.json`` entries (names ``img_name``, sorted by name). All
    must share one size (ours do); a camera's ``rotation`` is camera-to-world, ``position`` its centre."""
    try:
        ents = sorted(entries, key=lambda e: str(e["img_name"]))
        sizes = {(int(e["width"]), int(e["height"])) for e in ents}
        c2w = np.tile(np.eye(4), (len(ents), 1, 1))
        c2w[:, :3, :3] = np.array([e["rotation"] for e in ents], np.float64)
        c2w[:, :3, 3] = np.array([e["position"] for e in ents], np.float64)
        fx = np.array([float(e["fx"]) for e in ents])
        fy = np.array([float(e["fy"]) for e in ents])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{where}: unexpected layout ({e}); expected graphdeco's img_name, width, height, "
                         f"position, rotation, fx, fy per camera") from None
    if len(sizes) != 1:
        raise InputError(f"{where}: cameras of several sizes ({sorted(sizes)}); ssgwarp runs hold one size")
    if not np.isfinite(c2w).all():
        raise InputError(f"{where}: NaN/inf in the poses")
    (w, h), = sizes
    Ks = np.zeros((len(ents), 3, 3))
    Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = fx, fy, w / 2.0, h / 2.0, 1.0
    return Cameras(torch.from_numpy(np.linalg.inv(c2w)).float(), torch.from_numpy(Ks).float(), w, h,
                   [str(e["img_name"]) for e in ents])


# ----------------------------------------------------------------------------- nerfstudio
def nerfstudio_to_capture(dataparser_transforms: str | Path, transforms_json: Optional[dict] = None,
                          colmap_in_dataset: bool = False) -> Similarity:
    """The similarity from splatfacto's frame (what ``ns-export gaussian-splat`` writes) to the frame
    of the dataset's ``transforms.json``. ``transform`` and ``scale`` take the original data frame to
    splatfacto's; the transforms.json frame is ``applied_transform`` of the original (nerfstudio
    assumes ``[[0,1,0,0],[1,0,0,0],[0,0,-1,0]]`` for a dataset with ``colmap/sparse/0`` and no
    ``applied_transform``; none otherwise)."""
    path = Path(dataparser_transforms)
    d = read_json(path)
    try:
        T = Similarity.from_matrix(np.asarray(d["transform"], np.float64))
        s = float(d["scale"])
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: expected 'transform' (3x4) and 'scale' ({e})") from None
    if not s > 0:
        raise InputError(f"{path}: scale {s} must be positive")
    meta = transforms_json or {}
    try:   # (nerfstudio multiplies the saved scale by an applied_scale after scaling the poses)
        s /= float(meta.get("applied_scale", 1.0))
    except (TypeError, ValueError, ZeroDivisionError):
        raise InputError(f"transforms.json: applied_scale {meta.get('applied_scale')!r} is not a positive number") \
            from None
    to_dp = Similarity(s) @ T                          # original -> splatfacto
    applied = meta.get("applied_transform")
    if applied is None and colmap_in_dataset:
        applied = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]
    A = Similarity() if applied is None else Similarity.from_matrix(np.asarray(applied, np.float64))
    return A @ to_dp.inverse()                          # splatfacto -> original -> transforms.json


def match_names(a: Sequence[str], b: Sequence[str]) -> list[tuple[int, int]]:
    """Index pairs of names equal up to folder and extension."""
    key = lambda n: Path(str(n)).stem  # noqa: E731
    idx = {}
    for j, n in enumerate(b):
        idx.setdefault(key(n), j)
    return [(i, idx[key(n)]) for i, n in enumerate(a) if key(n) in idx]
