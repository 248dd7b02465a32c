"""The size of a style's strokes and patterns, and the style scale that shows them in the views (``--style-scale auto``).

:func:`stroke_period` measures the style image's dominant period: the peak of its whitened power spectrum
(``f^2 |FFT(L)|^2`` of the lightness, averaged over rings of 1/4 octave; a painting's spectrum falls about as
``1/f^2``, so what stands out after whitening is the scale its strokes, dots and tesserae repeat at). A stripe
pattern of period ``p`` pixels measures ``p`` (to the 1/4-octave bin).

Without Stage 1 the style image is resized so that its shorter side equals the views' (:func:`ssgwarp.core.imaging.fit_style`,
scale 1): its strokes then cover the same fraction of a view as of the painting. At a small training resolution
that fraction can be a pixel or two, below what the capture's splats and Stage 2's features can paint; at a large
one it can exceed the features' widest window, so Stage 2 sees only pieces of each stroke (arcs instead of
circles). :func:`auto_style_scale` picks the scale that puts the measured period inside the features' reach
``[PERIOD_MIN, PERIOD_MAX]`` view pixels, the nearest scale to 1 that does (1 when it already is).
"""
from __future__ import annotations

import math

import torch

from ..core.imaging import rgb_to_lab
from ..errors import InputError

PERIOD_MIN = 6.0     # view pixels: below this a stroke is a speckle the splats blur away
PERIOD_MAX = 24.0    # view pixels: the patch features' widest window (5 px at 1/4 resolution) is about 20 px
SCALE_RANGE = (0.25, 4.0)   # --style-scale's range
BINS_PER_OCTAVE = 4


def stroke_period(style: torch.Tensor, shortest: float = 2.0) -> float:
    """The dominant period, in pixels of ``style [H, W, 3]`` (values 0..1), between ``shortest`` and a quarter of the
    shorter side: the centre of the 1/4-octave ring where the whitened lightness spectrum peaks (module docs)."""
    if style.ndim != 3 or style.shape[-1] != 3 or min(style.shape[:2]) < 16:
        raise InputError(f"stroke_period: expected a style image [H, W, 3] of at least 16 px, got {tuple(style.shape)}")
    lum = rgb_to_lab(style.double().clamp(0, 1))[..., 0]
    H, W = lum.shape
    win = torch.hann_window(H, periodic=False, dtype=lum.dtype)[:, None] * \
        torch.hann_window(W, periodic=False, dtype=lum.dtype)[None, :]
    power = torch.fft.fft2((lum - lum.mean()) * win).abs() ** 2
    fy, fx = torch.fft.fftfreq(H, dtype=lum.dtype)[:, None], torch.fft.fftfreq(W, dtype=lum.dtype)[None, :]
    f = torch.sqrt(fy ** 2 + fx ** 2)
    lo, hi = 4.0 / min(H, W), 1.0 / shortest                      # frequencies (cycles per pixel)
    edges = torch.tensor([lo * 2 ** (k / BINS_PER_OCTAVE) for k in
                          range(int(math.log2(hi / lo) * BINS_PER_OCTAVE) + 2)], dtype=lum.dtype)
    which = torch.bucketize(f.reshape(-1), edges) - 1
    ok = (which >= 0) & (which < len(edges) - 1)
    white = (f ** 2 * power).reshape(-1)
    energy = torch.zeros(len(edges) - 1, dtype=lum.dtype).index_add_(0, which[ok], white[ok])
    count = torch.bincount(which[ok], minlength=len(edges) - 1).to(lum.dtype)
    ring = energy / count.clamp_min(1)
    ring = torch.where(count > 0, ring, torch.zeros_like(ring))
    k = int(torch.argmax(ring))
    return 1.0 / math.sqrt(float(edges[k]) * float(edges[k + 1]))


def auto_style_scale(style: torch.Tensor, height: int, width: int) -> tuple[float, float]:
    """``(scale, period in view pixels at scale 1)`` for views of ``height x width``: the style's
    :func:`stroke_period` as it lands in a view at scale 1 (its shorter side fitted to the views'), and the
    scale nearest 1 that puts it in ``[PERIOD_MIN, PERIOD_MAX]`` (within :data:`SCALE_RANGE`)."""
    period = stroke_period(style) * min(height, width) / min(style.shape[:2])
    scale = min(max(1.0, PERIOD_MIN / period), PERIOD_MAX / period) if period < PERIOD_MIN or period > PERIOD_MAX else 1.0
    return min(max(scale, SCALE_RANGE[0]), SCALE_RANGE[1]), period
