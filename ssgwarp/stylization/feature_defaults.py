"""The Stage 2 options left to the feature extractor, made concrete (:func:`resolve_for`).

A :class:`~ssgwarp.stylization.stage2.Stage2Config` leaves some options to the features it runs with
(``None`` or ``"auto"``): the style loss, the content and TV weights, the blend spread's weight, the colour map's
gain cap and whether it keeps the scene's texture. The values were measured per extractor on fern and the demo scene,
25 styles each (docs/stylize.md); VGG16's were not re-measured.
"""
from __future__ import annotations

from dataclasses import replace

TV_WEIGHT_FREE = 0.5    # weight-free random features (fern, 25 styles: worst consistency 1.29x/1.36x vs 1.55x/1.63x at 0.02)
TV_WEIGHT_VGG = 0.02    # VGG16 features (the weighted path; not re-measured, unchanged)
BLEND_WEIGHT_EDGES = 0.65   # the blend spread's weight on the edge features (demo + fern, 25 styles: docs/stylize.md)
COLOR_GAIN_EDGES = 1.0      # the colour map's gain cap on the edge features ...
COLOR_GAIN_OTHER = 1.3      # ... and on the others (random: measured; VGG16: not re-measured)
CONTENT_WEIGHT = 0.05       # the content term's weight on every extractor but ...
CONTENT_WEIGHT_PATCHES = 0.01   # ... the patch features, whose content term holds the scene's own patterns
                                # (fern, 25 styles: texture -67.9 % at 1.17x against -56.7 % at 1.09x with 0.05)


def _is_vgg(extractor) -> bool:
    return str(getattr(extractor, "name", "")).startswith("vgg16")


def _is_patches(extractor) -> bool:
    return str(getattr(extractor, "name", "")).startswith("patches:")


def _is_edges(extractor) -> bool:
    """Features blind to flat colour: ``random-edges``, ``random-strokes`` (zero-mean first-layer filters) and
    ``patches`` (centred windows); the same defaults suit all three: the colour transfer matches colour."""
    name = str(getattr(extractor, "name", ""))
    return "edges" in name.split(",") or name.startswith(("random-strokes:", "patches:"))


def style_loss_kind(cfg, extractor) -> str:
    """The style loss ``cfg`` asks for with this extractor (``auto``: NNFM on VGG16 features, else SW)."""
    if cfg.style_loss != "auto":
        return cfg.style_loss
    return "nnfm" if _is_vgg(extractor) else "sw"


def tv_weight_for(cfg, extractor) -> float:
    """The TV weight ``cfg`` asks for with this extractor: ``cfg.tv_weight`` when set, else
    :data:`TV_WEIGHT_FREE` on the weight-free random features and :data:`TV_WEIGHT_VGG` on VGG16
    (the same rule as ``style_loss="auto"``, :func:`style_loss_kind`)."""
    if cfg.tv_weight is not None:
        return float(cfg.tv_weight)
    return TV_WEIGHT_VGG if _is_vgg(extractor) else TV_WEIGHT_FREE


def resolve_for(cfg, extractor):
    """``cfg`` with the options it leaves to the extractor made concrete (``content_weight``, ``blend_weight``
    and ``color_max_gain`` None, ``color_detail`` ``auto``): on the weight-free edge features
    (``--extractor random-edges``, the weight-free default, ``random-strokes``, ``patches``) blend spread
    :data:`BLEND_WEIGHT_EDGES`, gain cap :data:`COLOR_GAIN_EDGES` and ``keep``; otherwise 0,
    :data:`COLOR_GAIN_OTHER` and ``off``; content weight :data:`CONTENT_WEIGHT_PATCHES` on the patch features,
    :data:`CONTENT_WEIGHT` on the others (measured on fern and the demo scene, 25 styles: docs/stylize.md).
    ``tv_weight`` keeps its own rule (:func:`tv_weight_for`). Values set explicitly are kept."""
    edges = _is_edges(extractor)
    over: dict = {}
    if cfg.content_weight is None:
        over["content_weight"] = CONTENT_WEIGHT_PATCHES if _is_patches(extractor) else CONTENT_WEIGHT
    if cfg.blend_weight is None:
        over["blend_weight"] = BLEND_WEIGHT_EDGES if edges else 0.0
    if cfg.color_max_gain is None:
        over["color_max_gain"] = COLOR_GAIN_EDGES if edges else COLOR_GAIN_OTHER
    if cfg.color_detail == "auto":
        over["color_detail"] = "keep" if edges else "off"
    return replace(cfg, **over) if over else cfg
