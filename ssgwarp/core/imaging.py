"""Image helpers shared by the stages: batches in ``[B, H, W, C]``, resizing, contact sheets.

:func:`rgb_to_lab` converts sRGB to CIE Lab (the colour transfer's and the style distance's
colour space), :func:`as_bhwc` takes an image or a batch (numpy or torch), :func:`resize_bhwc` resizes a batch
(bilinear, antialiased when shrinking), :func:`save_sheet` writes original | stylized pairs side
by side (atomically, :mod:`ssgwarp.core.fileio`), :func:`fit_style` scales a style image to a view's
shorter side (Stage 2's global targets, the metrics' Gram and style distances);
:func:`contact_sheet` (original | stylized | style rows) and :func:`plot_losses` draw on a bare
matplotlib Figure (no pyplot, nothing process-wide).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError
from .fileio import atomic_path, write_image


# D65 reference white and the sRGB -> XYZ matrix (IEC 61966-2-1)
_D65 = (0.95047, 1.0, 1.08883)
_RGB_TO_XYZ = ((0.4124564, 0.3575761, 0.1804375),
               (0.2126729, 0.7151522, 0.0721750),
               (0.0193339, 0.1191920, 0.9503041))


def rgb_to_lab(rgb: torch.Tensor) -> torch.Tensor:
    """CIE L*a*b* ``[..., 3]`` (D65; L in [0, 100]) of sRGB colours ``rgb [..., 3]`` (clamped to [0, 1])."""
    x = rgb.clamp(0.0, 1.0)
    lin = torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    m = torch.tensor(_RGB_TO_XYZ, dtype=lin.dtype, device=lin.device)
    xyz = lin @ m.T / torch.tensor(_D65, dtype=lin.dtype, device=lin.device)
    d = 6.0 / 29.0
    f = torch.where(xyz > d ** 3, xyz.clamp_min(1e-12) ** (1.0 / 3.0), xyz / (3 * d * d) + 4.0 / 29.0)
    L = 116.0 * f[..., 1] - 16.0
    a = 500.0 * (f[..., 0] - f[..., 1])
    b = 200.0 * (f[..., 1] - f[..., 2])
    return torch.stack([L, a, b], dim=-1)


def blur5(t: torch.Tensor) -> torch.Tensor:
    """Separable 5-tap Gaussian blur (sigma 1 px, replicate padding) of ``t [N, 1, H, W]``: one step of
    the Gaussian pyramids of the texture measures (style distance, the colour map's texture bands)."""
    ax = torch.arange(-2, 3, dtype=t.dtype, device=t.device)
    g = torch.exp(-ax ** 2 / 2.0)
    g = g / g.sum()
    t = F.conv2d(F.pad(t, (2, 2, 0, 0), mode="replicate"), g.view(1, 1, 1, 5))
    return F.conv2d(F.pad(t, (0, 0, 2, 2), mode="replicate"), g.view(1, 1, 5, 1))


def pyramid_down(t: torch.Tensor) -> torch.Tensor:
    """The next (half-size) level of a Gaussian pyramid: :func:`blur5`, then every other pixel."""
    return blur5(t)[..., ::2, ::2]


def as_bhwc(img) -> tuple[torch.Tensor, bool, bool]:
    """``(batch [B, H, W, C] tensor, was a single image, was numpy)`` of an image or a batch
    (numpy or torch): what a function taking either form works on."""
    was_np = not isinstance(img, torch.Tensor)
    t = torch.as_tensor(np.asarray(img) if was_np else img)
    squeeze = t.ndim == 3
    if t.ndim == 2:
        raise InputError("expected an image [H, W, C] or a batch [B, H, W, C], got [H, W]")
    if squeeze:
        t = t[None]
    if t.ndim != 4:
        raise InputError(f"expected an image [H, W, C] or [B, H, W, C], got shape {tuple(t.shape)}")
    return t, squeeze, was_np


def resize_nearest(ids: np.ndarray, width: int, height: int) -> np.ndarray:
    """``ids [h, w]`` resampled to ``[height, width]`` by nearest neighbour (pixel centres)."""
    h, w = ids.shape
    if (w, h) == (width, height):
        return ids
    ys = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return ids[ys[:, None], xs[None, :]]


def resize_bhwc(t: torch.Tensor, w: int, h: int) -> torch.Tensor:
    """``[B, H, W, C]`` → ``[B, h, w, C]`` bilinear (antialiased when shrinking)."""
    if t.shape[1] == h and t.shape[2] == w:
        return t
    x = t.permute(0, 3, 1, 2)
    dt = x.dtype
    x = x.float() if not x.is_floating_point() else x
    x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return x.to(dt).permute(0, 2, 3, 1)


def save_sheet(original, stylized, path: str | Path, gap: int = 4) -> Path:
    """Side-by-side sheet, one row per view: original | stylized (white gaps), written atomically."""
    def np_(x):
        x = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        return np.clip(x.astype(np.float32), 0.0, 1.0)

    a, b = np_(original), np_(stylized)
    if a.ndim == 3:
        a, b = a[None], b[None]
    if a.shape[0] != b.shape[0]:
        raise InputError(f"save_sheet: {a.shape[0]} originals but {b.shape[0]} stylized views")
    H, W = a.shape[1], a.shape[2]
    if b.shape[1:3] != (H, W):
        b = resize_bhwc(torch.from_numpy(b), W, H).numpy()
    rows = []
    for i in range(a.shape[0]):
        g = np.ones((H, gap, 3), np.float32)
        rows.append(np.concatenate([a[i, ..., :3], g, b[i, ..., :3]], axis=1))
        if i + 1 < a.shape[0]:
            rows.append(np.ones((gap, 2 * W + gap, 3), np.float32))
    return write_image(path, np.concatenate(rows, axis=0))


def fit_style(style: torch.Tensor, height: int, width: int, scale: float = 1.0) -> torch.Tensor:
    """Resize ``style [H_s, W_s, 3]`` so its shorter side equals ``scale * min(height, width)`` (aspect kept):
    ``[1,3,h,w]``. ``scale > 1`` makes the style's strokes and patterns larger in a view."""
    s = style.permute(2, 0, 1)[None]
    hs, ws = s.shape[-2:]
    k = max(1, round(scale * min(height, width))) / min(hs, ws)
    size = (max(1, round(hs * k)), max(1, round(ws * k)))
    if size == (hs, ws):
        return s
    return F.interpolate(s, size=size, mode="bilinear", align_corners=False, antialias=k < 1.0)


def plot_losses(path: Path, history: list[dict], title: str) -> None:
    """A PNG of the loss history (``total``, ``style``, ``content``, ``tv`` per logged step, log scale);
    nothing when the history is empty."""
    from matplotlib.figure import Figure

    if not history:
        return
    fig = Figure(figsize=(6, 3.5), dpi=100)
    ax = fig.subplots()
    steps = [h["step"] for h in history]
    for key in ("total", "style", "content", "tv"):
        if key in history[0]:
            ax.plot(steps, [h.get(key, float("nan")) for h in history], label=key)
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def contact_sheet(path: Path, originals: torch.Tensor, stylized: torch.Tensor, style: torch.Tensor,
                  names: Sequence[str], title: str = "") -> Path:
    """A PNG with one row per view: original | stylized | style (a bare matplotlib Figure: no pyplot)."""
    from matplotlib.figure import Figure

    n = len(originals)
    h, w = originals.shape[1:3]
    fig = Figure(figsize=(3 * 3.2, n * 3.2 * h / w + 0.6), dpi=110)
    axes = fig.subplots(n, 3, squeeze=False)
    for i in range(n):
        for j, (img, label) in enumerate([(originals[i], f"original {names[i]}"), (stylized[i], "stylized"),
                                          (style, "style")]):
            ax = axes[i, j]
            ax.imshow(img.detach().float().clamp(0, 1).cpu().numpy())
            ax.set_title(label, fontsize=8)
            ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


VIDEO_FPS = 15      # frames per second of the videos (stylize's path.gif, render --video)
VIDEO_SIDE = 512    # their longer side at most (a preview: the PNG frames are full size)
VIDEO_SUFFIXES = (".gif", ".mp4")


def mp4_writer_missing() -> str | None:
    """None when an MP4 can be written here (``imageio`` with ``imageio-ffmpeg``), else the line saying what
    to install."""
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return "MP4 needs the imageio and imageio-ffmpeg packages (pip install imageio imageio-ffmpeg); .gif needs nothing"
    return None


def write_video(path: Path, frames: list, fps: int = VIDEO_FPS, max_side: int = VIDEO_SIDE) -> Path:
    """A looping video of ``frames`` (``[H, W, 3]`` uint8 arrays) at ``fps`` frames per second, shrunk to at most
    ``max_side`` pixels on the longer side, written atomically: an animated GIF with Pillow (matplotlib's own
    dependency: no video codec needed), or, for a ``.mp4`` name, H.264 through ``imageio-ffmpeg`` when it is
    installed (sides rounded down to even). Returns ``path``."""
    from PIL import Image

    path = Path(path)
    kind = path.suffix.lower()
    if kind not in VIDEO_SUFFIXES:
        raise InputError(f"{path}: a video is a .gif or .mp4 file")
    if kind == ".mp4" and mp4_writer_missing():
        raise InputError(f"{path}: {mp4_writer_missing()}")
    if not frames:
        raise InputError("path video: no frames")
    h, w = frames[0].shape[:2]
    scale = min(1.0, max_side / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    if kind == ".mp4":
        size = (max(2, size[0] - size[0] % 2), max(2, size[1] - size[1] % 2))

    def frame(f):
        im = Image.fromarray(f)
        return im if im.size == size else im.resize(size, Image.Resampling.BOX)

    images = [frame(f) for f in frames]
    with atomic_path(path) as tmp:
        if kind == ".gif":
            # (octree quantisation: ~20x faster than the median cut of convert("P", ADAPTIVE) for a palette that
            # is ~0.7/255 further from the frame on average; benchmarks/writes.py)
            images = [im.quantize(255, method=Image.Quantize.FASTOCTREE) for im in images]
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps),
                           loop=0, disposal=1)
        else:
            import imageio.v2 as iio

            with iio.get_writer(tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", macro_block_size=1) as wr:
                for im in images:
                    wr.append_data(np.asarray(im.convert("RGB")))
    return path
