"""Key views: which views Stage 1 stylizes, rendered at the diffusion resolution.

Selection (:func:`select_keyviews`). Each camera becomes a point
``(c / s, w * f)`` where ``c`` is its centre, ``s`` the RMS distance of the
centres to their mean (1 when all centres coincide), ``f`` its unit viewing
direction and ``w`` the direction weight (1). Farthest-point sampling starts
from the camera nearest the mean point (the most typical view) and then adds,
one at a time, the camera whose distance to the chosen set is largest. Ties go
to the lowest index, so the choice is deterministic. ``ids`` given by the user
are taken as they are (validated).

Resize/pad rule (:func:`diffusion_size`, :func:`to_diffusion`,
:func:`from_diffusion`). An image of ``w x h`` is scaled by
``s = max_side / max(w, h)`` to ``rw x rh = round(w s) x round(h s)`` (aspect
kept), then padded on the right and bottom, by repeating the last column/row,
up to ``W x H``, the next multiples of 8. The inverse crops the top-left
``rw x rh`` and resizes back to ``w x h``. Key views are *rendered* straight at
``W x H`` with intrinsics scaled by ``(rw / w, rh / h)``, so their
"padding" strip shows real scene content and the same inverse applies.
``max_side`` must be a multiple of 8, so ``max_side = max(W, H)`` and the
inverse needs only the original size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras
from ..errors import InputError
from ..core.fileio import read_image, read_json, write_image, write_json
from ..core.imaging import as_bhwc, resize_bhwc, save_sheet
from ..core.palette import colorize_labels
from ..raster.rendering import background_tensor

__all__ = ["KeyViews", "select_keyviews", "diffusion_size", "content_size", "to_diffusion", "from_diffusion",
           "diffusion_cameras", "render_keyviews", "save_keyviews", "load_keyviews", "parse_ids"]


# -- selection ------------------------------------------------------------------------------------
def select_keyviews(cameras: Cameras, k: int = 4, ids: Optional[Sequence[int]] = None, *,
                    candidates: Optional[Sequence[int]] = None, direction_weight: float = 1.0) -> list[int]:
    """Indices (into ``cameras``) of ``k`` views that cover the scene.

    ``ids``: the user's choice, returned as given after validation.
    ``candidates``: restrict the choice to these indices (e.g. the training
    views); default all. When ``k`` exceeds the candidates, all are returned.
    Farthest-point sampling over centres and viewing directions (module docstring).
    """
    n = len(cameras)
    if ids is not None:
        ids = [int(i) for i in ids]
        bad = [i for i in ids if not 0 <= i < n]
        if bad:
            raise InputError(f"key view ids {bad} out of range: the run has {n} cameras (ids 0..{n - 1})")
        if len(set(ids)) != len(ids):
            raise InputError(f"key view ids {ids} contain duplicates")
        if not ids:
            raise InputError("key view ids: empty list")
        return ids
    if int(k) < 1:
        raise InputError(f"--keyviews must be >= 1, got {k}")
    cand = list(range(n)) if candidates is None else [int(i) for i in candidates]
    if not cand:
        raise InputError("no candidate cameras to choose key views from")
    if any(not 0 <= i < n for i in cand):
        raise InputError(f"candidate camera ids out of range 0..{n - 1}")
    if k >= len(cand):
        return list(cand)
    c2w = cameras.camtoworlds.detach().to("cpu", torch.float64)[cand]
    centers, fwd = c2w[:, :3, 3], torch.nn.functional.normalize(c2w[:, :3, 2], dim=-1)
    rel = centers - centers.mean(0)
    scale = float(rel.pow(2).sum(-1).mean().sqrt())
    scale = scale if scale > 1e-12 else 1.0
    feat = torch.cat([rel / scale, float(direction_weight) * fwd], dim=-1)
    dist_to_mean = (feat - feat.mean(0)).norm(dim=-1)
    first = int(torch.argmin(_round(dist_to_mean)))
    chosen = [first]
    mind = (feat - feat[first]).norm(dim=-1)
    while len(chosen) < k:
        nxt = int(torch.argmax(_round(mind)))   # argmax returns the first maximum: lowest index wins ties
        chosen.append(nxt)
        mind = torch.minimum(mind, (feat - feat[nxt]).norm(dim=-1))
    return [cand[i] for i in chosen]


def _round(x: torch.Tensor) -> torch.Tensor:
    # features are O(1): rounding to 1e-6 makes ties (symmetric rigs) robust to float32 camera noise
    return torch.round(x * 1e6) / 1e6


def parse_ids(text: Optional[str]) -> Optional[list[int]]:
    """``"0,5,9"`` → ``[0, 5, 9]``; None/empty → None."""
    if text is None or str(text).strip() == "":
        return None
    try:
        return [int(t) for t in str(text).replace(" ", "").split(",") if t != ""]
    except ValueError:
        raise InputError(f"--ids '{text}': expected comma-separated integers, e.g. 0,5,9") from None


# -- resize / pad rule ------------------------------------------------------------------------------
def _check_max_side(max_side: int) -> int:
    max_side = int(max_side)
    if max_side < 8 or max_side % 8:
        raise InputError(f"max_side must be a positive multiple of 8, got {max_side}")
    return max_side


def content_size(width: int, height: int, max_side: int = 512) -> tuple[int, int]:
    """``(rw, rh)``: the image scaled so its longer side is ``max_side``, aspect kept (before padding)."""
    max_side = _check_max_side(max_side)
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise InputError(f"bad image size {width}x{height}")
    s = max_side / max(width, height)
    return max(1, int(math.floor(width * s + 0.5))), max(1, int(math.floor(height * s + 0.5)))


def diffusion_size(width: int, height: int, max_side: int = 512) -> tuple[int, int]:
    """``(W, H)``: :func:`content_size` padded up to multiples of 8."""
    rw, rh = content_size(width, height, max_side)
    return 8 * math.ceil(rw / 8), 8 * math.ceil(rh / 8)


def to_diffusion(img, max_side: int = 512):
    """``[H, W, C]`` or ``[B, H, W, C]`` → the same at :func:`diffusion_size` (resize, then edge-pad right/bottom).

    Numpy in, numpy out; torch in, torch out.
    """
    t, squeeze, was_np = as_bhwc(img)
    h, w = t.shape[1], t.shape[2]
    rw, rh = content_size(w, h, max_side)
    W, H = diffusion_size(w, h, max_side)
    t = resize_bhwc(t, rw, rh)
    if (W, H) != (rw, rh):
        t = F.pad(t.permute(0, 3, 1, 2).float(), (0, W - rw, 0, H - rh), mode="replicate").to(t.dtype)
        t = t.permute(0, 2, 3, 1)
    t = t[0] if squeeze else t
    return t.numpy() if was_np else t


def from_diffusion(img, width: int, height: int):
    """Inverse of :func:`to_diffusion`: crop the top-left content and resize to ``width x height``."""
    t, squeeze, was_np = as_bhwc(img)
    H, W = t.shape[1], t.shape[2]
    max_side = max(H, W)
    if diffusion_size(width, height, max_side) != (W, H):
        raise InputError(f"a {W}x{H} image is not the diffusion size of {width}x{height} "
                         f"(expected {diffusion_size(width, height, max_side)})")
    rw, rh = content_size(width, height, max_side)
    t = resize_bhwc(t[:, :rh, :rw], int(width), int(height))
    t = t[0] if squeeze else t
    return t.numpy() if was_np else t


def diffusion_cameras(cameras: Cameras, size: tuple[int, int]) -> Cameras:
    """``cameras`` re-targeted to render ``size = (W, H)`` images under the resize/pad rule.

    ``size`` must be ``diffusion_size(cameras.width, cameras.height, max(size))``.
    """
    W, H = int(size[0]), int(size[1])
    max_side = max(W, H)
    expect = diffusion_size(cameras.width, cameras.height, max_side)
    if (W, H) != expect:
        raise InputError(f"key view size {W}x{H} does not follow the resize/pad rule for "
                         f"{cameras.width}x{cameras.height} images (use {expect[0]}x{expect[1]}, "
                         f"= diffusion_size(w, h, max_side={max_side}))")
    rw, rh = content_size(cameras.width, cameras.height, max_side)
    Ks = cameras.Ks.clone()
    Ks[:, 0, :] *= rw / cameras.width
    Ks[:, 1, :] *= rh / cameras.height
    return Cameras(cameras.viewmats.clone(), Ks, W, H, list(cameras.names))


# -- rendering ------------------------------------------------------------------------------------
@dataclass
class KeyViews:
    """K rendered key views at the diffusion resolution ``W x H``.

    rgb ``[K, H, W, 3]`` in [0, 1]; depth ``[K, H, W]`` expected depth (0 where
    alpha is 0); alpha ``[K, H, W]``; groups ``[K, H, W]`` long (argmax of
    the classifier's softmax at every pixel, background included — mask with
    ``alpha`` if needed) or None without a classifier; ids: camera indices in
    the run; cameras: the K cameras retargeted to ``W x H``; source_size:
    ``(w, h)`` of the run's cameras (for :func:`from_diffusion`).
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    groups: Optional[torch.Tensor]
    ids: list[int]
    cameras: Cameras
    source_size: tuple[int, int]
    num_groups: Optional[int] = None

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)``."""
        return int(self.rgb.shape[2]), int(self.rgb.shape[1])

    def to(self, device) -> "KeyViews":
        return KeyViews(self.rgb.to(device), self.depth.to(device), self.alpha.to(device),
                        None if self.groups is None else self.groups.to(device), list(self.ids),
                        self.cameras.to(device), self.source_size, self.num_groups)


@torch.no_grad()
def render_keyviews(scene, cameras: Cameras, ids: Sequence[int], size: tuple[int, int],
                    classifier: Optional[torch.nn.Module] = None, background: Optional[Sequence[float]] = None,
                    **raster_kwargs) -> KeyViews:
    """Render RGB, expected depth, alpha and (with ``classifier``) group maps of ``cameras[ids]`` at ``size``.

    One ``scene.render(..., render_mode="RGB+ED", identities=classifier is not None)``
    pass; ``classifier`` is the grouping ``nn.Linear(E, K)``. ``background``
    (RGB) is composited under the colour (identity channels get 0).
    """
    ids = [int(i) for i in ids]
    if not ids:
        raise InputError("render_keyviews: no key view ids")
    cams = diffusion_cameras(cameras[ids], size).to(scene.device)
    with_groups = classifier is not None
    kw = dict(raster_kwargs)
    if background is not None:
        bg = background_tensor(background, scene.means)
        if with_groups:
            bg = torch.cat([bg, bg.new_zeros(scene.identities.shape[1])])
        kw["backgrounds"] = bg[None].expand(len(ids), -1).contiguous()
    colors, alphas, _ = scene.render(cams, render_mode="RGB+ED", identities=with_groups, **kw)
    rgb = colors[..., :3].clamp(0.0, 1.0).float()
    depth = torch.nan_to_num(colors[..., -1].float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)
    alpha = alphas[..., 0].float()
    groups, k = None, None
    if with_groups:
        ident = colors[..., 3:-1]
        w = classifier.weight
        logits = classifier(ident.to(device=w.device, dtype=w.dtype))
        groups = torch.softmax(logits, dim=-1).argmax(dim=-1).to(device=rgb.device, dtype=torch.long)
        k = int(logits.shape[-1])
    return KeyViews(rgb, depth, alpha, groups, ids, cams, (cameras.width, cameras.height), k)


# -- files ----------------------------------------------------------------------------------------
def _file(j: int, what: str, ext: str) -> str:
    return f"kv{j:02d}_{what}.{ext}"


def save_keyviews(keyviews: KeyViews, out_dir: str | Path, stylized: Optional[torch.Tensor] = None,
                  extra: Optional[dict] = None) -> Path:
    """Write the key views to ``out_dir``; returns ``out_dir/keyviews.json``.

    Per view ``j``: ``kvJJ_rgb.png``, ``kvJJ_depth.exr`` (expected depth),
    ``kvJJ_alpha.png``; with groups ``kvJJ_groups.exr`` (labels as floats,
    exact) and ``kvJJ_groups.png`` (ssgwarp.core.palette colours); with
    ``stylized [K, H, W, 3]`` also ``kvJJ_stylized.png`` and ``sheet.png``
    (original | stylized). ``cameras.json`` holds the key-view cameras at the
    diffusion size; ``keyviews.json`` the ids, camera names, sizes and file
    names (plus ``extra``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kv = keyviews
    W, H = kv.size
    files = []
    for j in range(len(kv)):
        f = {"rgb": _file(j, "rgb", "png"), "depth": _file(j, "depth", "exr"), "alpha": _file(j, "alpha", "png")}
        write_image(out / f["rgb"], kv.rgb[j])
        write_image(out / f["depth"], kv.depth[j])
        write_image(out / f["alpha"], kv.alpha[j])
        if kv.groups is not None:
            f["groups"] = _file(j, "groups", "exr")
            f["groups_color"] = _file(j, "groups", "png")
            write_image(out / f["groups"], kv.groups[j].float())
            write_image(out / f["groups_color"], colorize_labels(kv.groups[j], kv.num_groups))
        if stylized is not None:
            f["stylized"] = _file(j, "stylized", "png")
            write_image(out / f["stylized"], stylized[j])
        files.append(f)
    if stylized is not None:
        save_sheet(kv.rgb, stylized, out / "sheet.png")
    kv.cameras.save(out / "cameras.json")
    meta = {
        "ids": list(kv.ids),
        "names": list(kv.cameras.names),
        "width": W, "height": H,
        "source_width": int(kv.source_size[0]), "source_height": int(kv.source_size[1]),
        "max_side": max(W, H),
        "content_size": list(content_size(kv.source_size[0], kv.source_size[1], max(W, H))),
        "resize_rule": "scale longer side to max_side, round, pad right/bottom to multiples of 8 "
                       "(ssgwarp.stylization.keyviews.from_diffusion inverts it)",
        "num_groups": kv.num_groups,
        "stylized": stylized is not None,
        "files": files,
    }
    if extra:
        meta.update(extra)
    write_json(out / "keyviews.json", meta)
    return out / "keyviews.json"


def load_keyviews(out_dir: str | Path, device="cpu") -> tuple[KeyViews, Optional[torch.Tensor]]:
    """Read what :func:`save_keyviews` wrote: ``(KeyViews, stylized [K, H, W, 3] or None)``."""
    out = Path(out_dir)
    meta = read_json(out / "keyviews.json")
    try:
        files = meta["files"]
        cams = Cameras.load(out / "cameras.json")
        rgb = torch.stack([torch.from_numpy(read_image(out / f["rgb"], 3)) for f in files])
        depth = torch.stack([torch.from_numpy(read_image(out / f["depth"])[..., 0]) for f in files])
        alpha = torch.stack([torch.from_numpy(read_image(out / f["alpha"])[..., 0]) for f in files])
        groups = None
        if all("groups" in f for f in files) and files:
            groups = torch.stack([torch.from_numpy(read_image(out / f["groups"])[..., 0]).round().long()
                                  for f in files])
        stylized = None
        if meta.get("stylized") and all("stylized" in f for f in files):
            stylized = torch.stack([torch.from_numpy(read_image(out / f["stylized"], 3)) for f in files])
        kv = KeyViews(rgb, depth, alpha, groups, [int(i) for i in meta["ids"]], cams,
                      (int(meta["source_width"]), int(meta["source_height"])), meta.get("num_groups"))
    except (KeyError, TypeError) as e:
        raise InputError(f"{out / 'keyviews.json'}: unexpected layout ({e}); re-run `ssgwarp keyviews`") from None
    return kv.to(device), (None if stylized is None else stylized.to(device))
