"""Instance masks for every training view (``ssgwarp masks``): Segment Anything, then cross-view association.

1. **Segment** each training view with the Segment Anything model (``transformers``
   ``SamModel``; weights ``facebook/sam-vit-base`` resolved by :mod:`ssgwarp.services.weights`: ``--sam
   PATH``, ``SSGWARP_SAM``, the Hugging Face cache, a download on first use unless offline): the image is embedded once, a regular grid of
   ``points_per_side``² point prompts is decoded in batches of ``points_per_batch``
   (three candidate masks per point), candidates are kept when their predicted IoU
   exceeds ``pred_iou_thresh`` and their stability score (the IoU of the mask
   thresholded at ``+offset`` and at ``-offset`` logits) exceeds ``stability_thresh``,
   and duplicates are removed by greedy non-maximum suppression on mask IoU
   (``nms_thresh``, best predicted IoU first). Masks smaller than ``min_area`` of the
   view are dropped; the rest are painted into one label map per view, largest first,
   so smaller masks (parts, objects on a table) stay on top. Each view's map is
   written to ``RUN/sam_masks/`` as soon as it is done (``--resume`` keeps them).
   ``--view-masks DIR`` skips this step and takes per-view masks made elsewhere
   (ids need not agree between views).
2. **Associate** the views' masks through the reconstruction
   (:mod:`ssgwarp.grouping.association`) into instance ids that agree across views.
3. **Write** Gaussian Grouping's layout ``RUN/object_mask/<image stem>.png`` (0 =
   background, 1..K instances, ``ignore_id`` = 255, or 65535 for 16-bit masks when
   K > 254, on pixels no label dominates) for every camera of the run, and the
   record ``RUN/masks.json``. ``ssgwarp group RUN`` then trains on them (``--masks
   auto`` finds ``RUN/object_mask`` first), as does ``--joint``.

Public API:
    MaskConfig, SamSegmenter
    load_sam(path, device)                           -> SamSegmenter
    point_grid(n, width, height)                     -> [n*n, 2] prompt points in pixels
    stability_scores(logits, threshold, offset)      -> [M]
    select_masks(logits, iou, config)                -> (kept logits, scores)
    mask_nms(masks, scores, iou_thresh)              -> kept indices
    paint_label_map(masks)                           -> [H, W] long
    make_masks(scene_dir, ...)                       -> the masks.json record (what the CLI runs)
    (the command: :mod:`ssgwarp.commands.masks`)
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..services import weights
from .association import AssociationConfig, associate
from ..errors import InputError, SsgwarpError
from ..core.fileio import atomic_path, read_json, write_json
from .mask_files import load_masks, read_id_image
from ..services.runs import Run, claim

Tensor = torch.Tensor
FORMAT = "ssgwarp-masks-1"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class MaskConfig:
    """Automatic mask generation knobs (defaults: the Segment Anything paper's automatic generator).

    points_per_side: the prompt grid is points_per_side x points_per_side over the image.
    points_per_batch: prompts decoded together (memory: ~4 MB per prompt at ViT-B sizes).
    pred_iou_thresh: keep masks whose predicted IoU exceeds it.
    stability_thresh, stability_offset: keep masks whose stability score (IoU of the mask
        thresholded at ``mask_threshold + offset`` and ``- offset`` logits) exceeds it.
    nms_thresh: a mask overlapping a better one by more than this IoU is dropped.
    min_area: masks covering less than this share of the view are dropped.
    mask_threshold: logit threshold of a mask.
    """

    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou_thresh: float = 0.88
    stability_thresh: float = 0.95
    stability_offset: float = 1.0
    nms_thresh: float = 0.7
    min_area: float = 0.0005
    mask_threshold: float = 0.0

    def validate(self) -> "MaskConfig":
        if self.points_per_side < 1 or self.points_per_batch < 1:
            raise InputError(f"--points-per-side and --points-per-batch must be >= 1, got "
                             f"{self.points_per_side} and {self.points_per_batch}")
        for name in ("pred_iou_thresh", "stability_thresh", "nms_thresh", "min_area"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"--{name.replace('_', '-')} must be in [0, 1], got {v}")
        if self.stability_offset <= 0:
            raise InputError(f"stability offset must be > 0, got {self.stability_offset}")
        return self


# -- the model -----------------------------------------------------------------------------------

@dataclass
class SamSegmenter:
    """A loaded ``SamModel`` and its input convention (longest side ``image_size``, normalisation)."""

    model: torch.nn.Module
    image_size: int
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    source: str = ""

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def embed(self, image: Tensor) -> tuple[Tensor, float, tuple[int, int]]:
        """``image [H, W, 3]`` in [0, 1] → ``(embeddings [1, C, h, w], scale, (resized H, W))``.

        The image is resized so that its longer side is ``image_size`` (bilinear, antialiased),
        normalised and zero-padded to a square, as the Segment Anything image encoder expects.
        """
        dev = self.device
        H, W = image.shape[:2]
        s = self.image_size / max(H, W)
        h, w = max(1, int(H * s + 0.5)), max(1, int(W * s + 0.5))
        x = image.to(dev, torch.float32).permute(2, 0, 1)[None]
        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        mean = torch.tensor(self.mean, device=dev).view(1, 3, 1, 1)
        std = torch.tensor(self.std, device=dev).view(1, 3, 1, 1)
        x = F.pad((x - mean) / std, (0, self.image_size - w, 0, self.image_size - h))
        dtype = next(self.model.parameters()).dtype
        with torch.no_grad():
            emb = self.model.get_image_embeddings(x.to(dtype))
        return emb, s, (h, w)

    def decode(self, embeddings: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
        """Point prompts ``[P, 2]`` (pixels of the resized image) → ``(logits [P, 3, m, m], iou [P, 3])``
        (low-resolution mask logits over the padded square)."""
        dev = self.device
        pts = points.to(dev, torch.float32)[None, :, None, :]
        labels = torch.ones(pts.shape[:3], dtype=torch.long, device=dev)
        with torch.no_grad():
            out = self.model(image_embeddings=embeddings, input_points=pts.to(embeddings.dtype),
                             input_labels=labels, multimask_output=True)
        return out.pred_masks[0].float(), out.iou_scores[0].float()


def load_sam(path: str | Path, device=None) -> SamSegmenter:
    """Load a transformers ``SamModel`` folder (``config.json`` + weights) for inference."""
    weights.check_kernels_package()
    from transformers import SamModel
    from transformers.utils import logging as tlog

    path = Path(path)
    verbosity = tlog.get_verbosity()
    tlog.set_verbosity_error()
    bars = tlog.is_progress_bar_enabled()
    tlog.disable_progress_bar()
    try:
        model = SamModel.from_pretrained(str(path), local_files_only=True)
    except (OSError, ValueError, KeyError, RuntimeError) as e:
        raise weights.load_error("sam", path, e) from None
    finally:
        tlog.set_verbosity(verbosity)
        if bars:
            tlog.enable_progress_bar()
    model = model.to(device if device is not None else "cpu").eval()
    mean, std = IMAGENET_MEAN, IMAGENET_STD
    pre = path / "preprocessor_config.json"
    if pre.is_file():
        cfg = read_json(pre)
        mean = tuple(float(v) for v in cfg.get("image_mean", mean))
        std = tuple(float(v) for v in cfg.get("image_std", std))
    return SamSegmenter(model=model, image_size=int(model.config.vision_config.image_size), mean=mean, std=std,
                        source=str(path))


# -- automatic mask generation -----------------------------------------------------------------------

def point_grid(n: int, width: int, height: int) -> Tensor:
    """``[n*n, 2]`` (x, y) prompt points in pixels: the centres of an n x n grid of cells over the image."""
    t = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    ys, xs = torch.meshgrid(t * height, t * width, indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1).float()


def stability_scores(logits: Tensor, threshold: float = 0.0, offset: float = 1.0) -> Tensor:
    """``[M]``: area above ``threshold + offset`` over area above ``threshold - offset`` of ``logits [M, ...]``
    (1 for a mask whose edges are sharp; 0 for an empty mask)."""
    flat = logits.reshape(logits.shape[0], -1)
    inner = (flat > threshold + offset).sum(dim=1).float()
    outer = (flat > threshold - offset).sum(dim=1).float()
    return torch.where(outer > 0, inner / outer.clamp_min(1), torch.zeros_like(outer))


def mask_iou(masks: Tensor) -> Tensor:
    """``[M, M]`` pairwise IoU of boolean masks ``[M, ...]``."""
    flat = masks.reshape(masks.shape[0], -1).float()
    inter = flat @ flat.T
    area = flat.sum(dim=1)
    union = area[:, None] + area[None, :] - inter
    return torch.where(union > 0, inter / union.clamp_min(1), torch.zeros_like(union))


def mask_nms(masks: Tensor, scores: Tensor, iou_thresh: float) -> Tensor:
    """Greedy non-maximum suppression: indices (best first) of the masks kept, a mask being dropped when it
    overlaps a kept, better-scored one by IoU > ``iou_thresh``."""
    if masks.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long)
    order = torch.argsort(scores.cpu(), descending=True, stable=True)
    iou = mask_iou(masks[order.to(masks.device)]).cpu().numpy()
    m = iou.shape[0]
    dropped = np.zeros(m, dtype=bool)
    keep = []
    for i in range(m):
        if dropped[i]:
            continue
        keep.append(i)
        dropped |= iou[i] > iou_thresh
    return order[torch.as_tensor(keep, dtype=torch.long)]


def select_masks(logits: Tensor, iou: Tensor, config: MaskConfig) -> tuple[Tensor, Tensor]:
    """Filter candidate masks: ``logits [M, h, w]``, predicted ``iou [M]`` → the survivors of the predicted-IoU
    and stability filters and of non-maximum suppression, ``(logits [K, h, w], scores [K])``, best first."""
    keep = iou > config.pred_iou_thresh
    if config.stability_thresh > 0:
        keep &= stability_scores(logits, config.mask_threshold, config.stability_offset) > config.stability_thresh
    logits, iou = logits[keep], iou[keep]
    binary = logits > config.mask_threshold
    nonempty = binary.flatten(1).any(dim=1)
    logits, iou, binary = logits[nonempty], iou[nonempty], binary[nonempty]
    idx = mask_nms(binary, iou, config.nms_thresh).to(logits.device)
    return logits[idx], iou[idx]


def paint_label_map(masks: Tensor) -> Tensor:
    """``masks [M, H, W]`` bool → ``[H, W]`` long: pixel = index of the smallest mask covering it, -1 where none
    does (masks are painted largest first, so smaller ones stay on top)."""
    M, H, W = masks.shape
    out = torch.full((H, W), -1, dtype=torch.long, device=masks.device)
    if M == 0:
        return out
    area = masks.flatten(1).sum(dim=1)
    for i in torch.argsort(area, descending=True, stable=True).tolist():
        out[masks[i]] = i
    return out


def generate_masks(sam: SamSegmenter, image: Tensor, config: MaskConfig = MaskConfig(),
                   out_size: Optional[tuple[int, int]] = None) -> tuple[Tensor, Tensor]:
    """Automatic masks of one ``image [H, W, 3]`` in [0, 1].

    Returns ``(masks [K, h, w] bool, scores [K])`` at ``out_size = (h, w)`` (default the image's size),
    best predicted IoU first, masks smaller than ``config.min_area`` of the image dropped.
    """
    H, W = image.shape[:2]
    oh, ow = out_size if out_size is not None else (H, W)
    emb, s, (rh, rw) = sam.embed(image)
    pts = point_grid(config.points_per_side, W, H) * s
    kept_l, kept_s = [], []
    for b in range(0, pts.shape[0], config.points_per_batch):
        logits, iou = sam.decode(emb, pts[b:b + config.points_per_batch])
        m = logits.shape[-1]
        vh = max(1, round(rh * m / sam.image_size))       # the part of the square the image fills
        vw = max(1, round(rw * m / sam.image_size))
        lg = logits[..., :vh, :vw].reshape(-1, vh, vw)
        sc = iou.reshape(-1)
        keep = sc > config.pred_iou_thresh
        if config.stability_thresh > 0:
            keep &= stability_scores(lg, config.mask_threshold, config.stability_offset) > config.stability_thresh
        kept_l.append(lg[keep].half() if lg.is_cuda else lg[keep])
        kept_s.append(sc[keep])
    logits = torch.cat(kept_l).float() if kept_l else torch.zeros(0, 1, 1)
    scores = torch.cat(kept_s) if kept_s else torch.zeros(0)
    # the filters already ran per batch: only the suppression is left
    logits, scores = select_masks(logits, scores, MaskConfig(**{**asdict(config), "pred_iou_thresh": -1.0,
                                                                 "stability_thresh": 0.0}))
    if logits.shape[0] == 0:
        return torch.zeros(0, oh, ow, dtype=torch.bool, device=logits.device), scores
    masks = []
    for c in range(0, logits.shape[0], 32):
        up = F.interpolate(logits[c:c + 32, None], size=(oh, ow), mode="bilinear", align_corners=False)
        masks.append(up[:, 0] > config.mask_threshold)
    masks = torch.cat(masks)
    big = masks.flatten(1).sum(dim=1) >= max(1.0, config.min_area * oh * ow)
    return masks[big], scores[big]


# -- mask images ------------------------------------------------------------------------------------

def write_id_image(path: str | Path, ids: np.ndarray, bits: int = 16) -> Path:
    """Write ``ids [H, W]`` (non-negative integers) as a single-channel 8- or 16-bit PNG, atomically."""
    import OpenImageIO as oiio

    path = Path(path)
    ids = np.asarray(ids)
    top = (1 << bits) - 1
    if ids.size and (ids.min() < 0 or ids.max() > top):
        raise ValueError(f"write_id_image: ids must be in 0..{top}")
    fmt, dt = ("uint8", np.uint8) if bits == 8 else ("uint16", np.uint16)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create("png")
        if out is None or not out.open(str(tmp), oiio.ImageSpec(ids.shape[1], ids.shape[0], 1, fmt)):
            raise OSError(f"{path}: cannot write mask image ({oiio.geterror()})")
        out.write_image(np.ascontiguousarray(ids.astype(dt)[..., None]))
        out.close()
    return path


def _stem(name: str) -> str:
    return Path(name).stem


# -- the command on a run --------------------------------------------------------------------------------

def _segment_views(scene_dir: Path, data, views: Sequence[int], sam: SamSegmenter, config: MaskConfig,
                   resume: bool, progress: bool) -> tuple[Tensor, list[dict]]:
    """SAM label maps of ``views`` (``[V, H, W]`` long, -1 uncovered), each saved to ``sam_masks/`` when done."""
    from ..core.progress import tqdm

    cams = data.cameras
    raw_dir = scene_dir / "sam_masks"
    settings = {"weights": sam.source, "image_size": sam.image_size, "config": asdict(config),
                "size": [cams.width, cams.height]}
    if resume and (raw_dir / "settings.json").is_file() and read_json(raw_dir / "settings.json") != settings:
        raise InputError(f"{raw_dir} was made with other settings or weights ({raw_dir / 'settings.json'}); "
                         "rerun with the same ones, or with --force to start over")
    write_json(raw_dir / "settings.json", settings)
    out = torch.full((len(views), cams.height, cams.width), -1, dtype=torch.long)
    info = []
    bar = tqdm(views, desc="segment anything", unit="view", disable=not progress)
    for j, i in enumerate(bar):
        name = cams.names[i]
        path = raw_dir / f"{_stem(name)}.png"
        t0 = time.perf_counter()
        if resume and path.is_file():
            ids = torch.from_numpy(read_id_image(path)).long() - 1     # stored +1: 0 = uncovered
            if tuple(ids.shape) != (cams.height, cams.width):
                raise InputError(f"{path}: {ids.shape[1]}x{ids.shape[0]} but the views are "
                                 f"{cams.width}x{cams.height}; rerun with --force")
            out[j] = ids
            info.append({"name": name, "masks": int(ids.max()) + 1, "resumed": True})
            continue
        masks, scores = generate_masks(sam, data.images[i], config, out_size=(cams.height, cams.width))
        lab = paint_label_map(masks).cpu()
        write_id_image(path, (lab + 1).numpy(), bits=16)
        out[j] = lab
        info.append({"name": name, "masks": int(masks.shape[0]),
                     "mean_predicted_iou": float(scores.mean()) if scores.numel() else None,
                     "seconds": round(time.perf_counter() - t0, 3)})
        bar.set_postfix(masks=int(masks.shape[0]))
    return out, info


def make_masks(scene_dir: str | Path, *, sam: Optional[str | Path] = None, view_masks: Optional[str | Path] = None,
               config: MaskConfig = MaskConfig(), association=None, weights_config: Optional[dict] = None,
               data_dir: Optional[str | Path] = None, device=None, force: bool = False, resume: bool = False,
               progress: bool = True, segmenter: Optional[SamSegmenter] = None) -> dict:
    """Instance masks for the run ``scene_dir`` (what ``ssgwarp masks`` runs); returns the ``masks.json`` record.

    Args:
        sam: explicit Segment Anything folder (else ``weights.require("sam")``: config, env, Hugging Face
            cache, a download unless offline; missing: one line naming ``ssgwarp weights --download sam``).
        view_masks: a folder of per-view masks ``<image stem>.png`` to associate instead of running SAM.
        association: :class:`ssgwarp.grouping.association.AssociationConfig`.
        segmenter: an already loaded :class:`SamSegmenter` (skips the weights lookup).
    """
    t_all = time.perf_counter()
    scene_dir = Path(scene_dir)
    config = config.validate()
    acfg = (association or AssociationConfig()).validate()
    out_dir = scene_dir / "object_mask"
    record_path = scene_dir / "masks.json"
    claimed = claim(scene_dir, ("object_mask", "masks.json"), force=force, resume=resume, what="instance masks",
                    scratch=("sam_masks",))
    device = torch.device(device) if device is not None else torch.device("cpu")
    seconds: dict[str, float] = {}
    if view_masks is None:
        seg = segmenter if segmenter is not None else None
        src = seg.source if seg is not None else str(weights.require("sam", sam, weights_config))  # before any work
    t0 = time.perf_counter()
    scene, data = Run.reconstruction(scene_dir).load(device, data_dir=data_dir, load_images=view_masks is None)
    cams = data.cameras
    train = list(data.train_ids)
    if not train:
        raise InputError(f"{scene_dir}: the run has no training views")
    seconds["load"] = time.perf_counter() - t0
    claimed.clear()   # (--force: the old masks, the raw SAM masks too)
    t0 = time.perf_counter()
    if view_masks is None:
        if seg is None:
            seg = load_sam(src, device)
        seconds["load_model"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        per_view, view_info = _segment_views(scene_dir, data, train, seg, config, resume, progress)
        source = {"kind": "segmenter", "model": "Segment Anything (transformers SamModel)", "weights": src,
                  "image_size": seg.image_size, "config": asdict(config), "raw_masks": "sam_masks/"}
    else:
        ms = load_masks(view_masks, [cams.names[i] for i in train], cams.width, cams.height)
        per_view = ms.targets
        view_info = [{"name": cams.names[i], "masks": int(torch.unique(per_view[j][per_view[j] >= 0]).numel())}
                     for j, i in enumerate(train)]
        source = {"kind": "view masks", "folder": str(view_masks)}
    seconds["segment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = associate(scene, cams[train], per_view.to(device), config=acfg, render_cameras=cams, progress=progress)
    seconds["associate"] = time.perf_counter() - t0
    k = res.num_instances
    bits = 8 if k < 255 else 16
    ignore_id = (1 << bits) - 1
    if k + 1 > ignore_id:
        raise SsgwarpError(f"association found {k} instances, more than a 16-bit mask can hold")
    masks = res.masks.cpu()
    for i, name in enumerate(cams.names):
        ids = torch.where(masks[i] >= 0, masks[i], torch.full_like(masks[i], ignore_id))
        write_id_image(out_dir / f"{_stem(name)}.png", ids.numpy(), bits=bits)
    for j, i in enumerate(train):
        view_info[j]["instances"] = sorted({x for x in res.mask_instance[j] if x > 0})
    cover = torch.bincount(masks[masks >= 0].flatten(), minlength=k + 1).double()
    record = {
        "format": FORMAT, "source": source, "num_instances": k, "background_id": 0, "ignore_id": ignore_id,
        "bits": bits, "object_mask": "object_mask/", "views": [cams.names[i] for i in range(len(cams))],
        "segmented_views": view_info, "train_views": [cams.names[i] for i in train],
        "instance_coverage": (cover / cover.sum().clamp_min(1)).tolist(),
        "pixels_ignored": float((masks < 0).double().mean()),
        "association": res.stats, "device": str(device),
        "seconds": {**{kk: round(v, 3) for kk, v in seconds.items()},
                    "total": round(time.perf_counter() - t_all, 3)},
    }
    write_json(record_path, record)
    return record


def read_record(mask_dir: str | Path) -> Optional[dict]:
    """The ``masks.json`` record of ``ssgwarp masks`` that wrote ``mask_dir`` (``RUN/object_mask``), or None."""
    mask_dir = Path(mask_dir)
    p = mask_dir.parent / "masks.json"
    if not p.is_file():
        return None
    try:
        rec = read_json(p)
    except (InputError, ValueError):
        return None
    if not isinstance(rec, dict) or rec.get("format") != FORMAT:
        return None
    try:
        same = (mask_dir.parent / rec.get("object_mask", "object_mask/")).resolve() == mask_dir.resolve()
    except OSError:
        return None
    return rec if same else None
