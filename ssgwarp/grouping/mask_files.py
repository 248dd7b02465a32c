"""Instance masks from files for Gaussian Grouping: ``object_mask/<image stem>.png``.

Integer ids consistent across views (8- or 16-bit, single channel or grey as RGB), resized by
nearest neighbour to the training resolution and made compact (:func:`load_masks`). Masks made
by ``ssgwarp masks`` (:mod:`ssgwarp.grouping.segment`) use the same layout.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..capture.lens import undistort_labels
from ..core.fileio import read_image_native
from ..core.imaging import resize_nearest  # noqa: F401  (re-exported: ssgwarp.grouping.stage)
from .pseudomasks import IGNORE

Tensor = torch.Tensor


def resolve_masks(masks, candidates: Sequence[Path]) -> Optional[Path]:
    """The mask folder a ``--masks`` value names: None/"none": mask-free (None); "auto": the first of the
    ``candidates`` folders that exists (none: mask-free); else the folder given."""
    if masks is None or str(masks).lower() == "none":
        return None
    if str(masks).lower() == "auto":
        return next((c for c in candidates if c.is_dir()), None)
    return Path(masks)


@dataclass
class MaskSet:
    """Instance masks at training resolution.

    targets: ``[C, H, W]`` long, compact ids ``0..M-1`` (``IGNORE`` where the
        mask holds ``ignore_id``); ``ids``: the original mask value of each
        compact id; ``num_groups``: K (>= M).
    """

    targets: Tensor
    ids: list[int]
    num_groups: int
    files: list[str]


def read_id_image(path: Path) -> np.ndarray:
    """``[H, W]`` integer ids of a single-channel (or grey-as-RGB) mask image, in its native bit depth."""
    arr = read_image_native(path, "native", what="mask image")
    if arr.dtype.kind == "f":
        raise InputError(f"{path}: mask images must hold integer ids (8- or 16-bit PNG), got float data")
    channels = arr.shape[2]
    if channels in (2, 4):          # drop alpha
        arr = arr[..., : channels - 1]
    if arr.shape[2] > 1 and not all(np.array_equal(arr[..., 0], arr[..., c]) for c in range(1, arr.shape[2])):
        raise InputError(f"{path}: a mask must be a single-channel image of integer ids, "
                         f"got {arr.shape[2]} differing colour channels")
    return arr[..., 0].astype(np.int64)


def find_mask(mask_dir: Path, name: str) -> Optional[Path]:
    """``mask_dir/<name>.png`` or ``mask_dir/<stem of name>.png``, whichever exists."""
    for cand in (mask_dir / f"{name}.png", mask_dir / f"{Path(name).stem}.png"):
        if cand.is_file():
            return cand
    return None


def _in_source_frame(shape, record: dict, width: int, height: int, tol: float) -> bool:
    """Whether a mask of ``shape`` is in the distorted source's frame rather than the training crop's."""
    h, w = shape[:2]
    W0, H0 = record["source_size"]
    if (w, h) == (W0, H0):
        return True
    same_source = abs((w / h) / (W0 / H0) - 1.0) <= tol
    same_crop = abs((w / h) / (width / height) - 1.0) <= tol
    return same_source and not same_crop


def load_masks(mask_dir: str | Path, names: Sequence[str], width: int, height: int, *,
               num_groups: Optional[int] = None, ignore_id: Optional[int] = None,
               required: Optional[Sequence[bool]] = None, aspect_tol: float = 0.02,
               undistortion: Optional[dict] = None) -> MaskSet:
    """Load Gaussian Grouping's ``object_mask/<image stem>.png`` for each of ``names``.

    Masks are resized by nearest neighbour to ``width`` x ``height``; their ids
    (all values but ``ignore_id``) are made compact in sorted order. K is the
    number of distinct ids unless ``num_groups`` is given.

    ``undistortion`` (``data.json``'s record of a distorted capture, whose images were undistorted
    into a pinhole crop): masks drawn on the original images (the source's size, or its aspect when
    that differs from the crop's) are brought into the crop through the same lens map
    (:func:`ssgwarp.capture.lens.undistort_labels`), so that no mask pixel lies where the image has no
    source; masks already in the crop's frame (``ssgwarp masks`` writes those) are taken as they are.
    ``names[i]`` is image i of the capture (the record's image numbering).

    ``required[i]`` False lets image i have no mask (its targets are all
    ``IGNORE``). Raises InputError for: a missing folder, a required mask
    missing (named), an aspect ratio that differs from the image's by more
    than ``aspect_tol`` (relative), a non-integer or colour mask, more ids than
    ``num_groups``.
    """
    mask_dir = Path(mask_dir)
    if not mask_dir.is_dir():
        raise InputError(f"--masks {mask_dir}: folder not found")
    required = [True] * len(names) if required is None else list(required)
    raw, files = [], []
    for name, req in zip(names, required):
        p = find_mask(mask_dir, name)
        if p is None:
            if req:
                raise InputError(f"{mask_dir}: no mask for image '{name}' (expected {mask_dir / (Path(name).stem + '.png')})")
            raw.append(None)
            files.append("")
            continue
        ids = read_id_image(p)
        if undistortion is not None and _in_source_frame(ids.shape, undistortion, width, height, aspect_tol):
            ids = undistort_labels(undistortion, len(raw), ids, what=str(p))
        h, w = ids.shape
        if abs((w / h) / (width / height) - 1.0) > aspect_tol:
            raise InputError(f"{p}: mask is {w}x{h} (aspect {w / h:.3f}) but image '{name}' is trained at "
                             f"{width}x{height} (aspect {width / height:.3f}); masks must match the images' aspect ratio")
        raw.append(resize_nearest(ids, width, height))
        files.append(str(p))
    if all(r is None for r in raw):
        raise InputError(f"{mask_dir}: no masks found for any image")
    values = np.unique(np.concatenate([r.reshape(-1) for r in raw if r is not None]))
    if ignore_id is not None:
        values = values[values != ignore_id]
    m = int(values.size)
    if m == 0:
        raise InputError(f"{mask_dir}: the masks hold no ids (every pixel is the ignore id {ignore_id})")
    k = m if num_groups is None else int(num_groups)
    if m > k:
        shown = ", ".join(str(int(v)) for v in values[:12]) + (" ..." if m > 12 else "")
        raise InputError(f"{mask_dir}: the masks hold {m} distinct ids ({shown}) but --groups is {k}; "
                         f"raise --groups to at least {m} or leave it out")
    lut = {int(v): i for i, v in enumerate(values)}
    targets = torch.full((len(names), height, width), IGNORE, dtype=torch.long)
    for i, r in enumerate(raw):
        if r is None:
            continue
        compact = np.full(r.shape, IGNORE, dtype=np.int64)
        for v, j in lut.items():
            compact[r == v] = j
        targets[i] = torch.from_numpy(compact)
    return MaskSet(targets=targets, ids=[int(v) for v in values], num_groups=k, files=files)
