"""A scene's groups (Gaussian Grouping's product, read by the stages after it): the linear classifier of the
identity encodings that ``ssgwarp group`` trained (``SCENE_DIR/groups/``, :func:`load_groups`), the group maps it
gives rendered views (:func:`render_group_maps`, :func:`group_labels`) and each Gaussian's own group
(:func:`gaussian_groups`). Training them: :mod:`ssgwarp.grouping`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from ..core.progress import tqdm

from ..core.cameras import Cameras
from ..core.fileio import read_json
from ..errors import InputError
from .scene import GaussianScene

Tensor = torch.Tensor


@dataclass
class GroupModel:
    """A trained group classifier: ``classifier`` (``nn.Linear`` E→K), ``num_groups`` K, ``dim`` E, ``info`` (groups.json)."""

    classifier: torch.nn.Linear
    num_groups: int
    dim: int
    info: dict = field(default_factory=dict)


def _copy_linear(classifier: torch.nn.Linear, device, dtype) -> torch.nn.Linear:
    lin = torch.nn.Linear(classifier.in_features, classifier.out_features, device=device, dtype=dtype)
    with torch.no_grad():
        lin.weight.copy_(classifier.weight)
        lin.bias.copy_(classifier.bias)
    return lin


def _iter_group_probs(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                      progress: bool = False, **raster_kwargs):
    """Yield ``probs [H, W, K]`` camera by camera."""
    if scene.identities is None:
        raise InputError("scene has no identity encodings: run `ssgwarp group` first")
    if scene.identities.shape[1] != classifier.in_features:
        raise InputError(f"identity length {scene.identities.shape[1]} does not match the classifier's "
                         f"input {classifier.in_features}")
    clf = _copy_linear(classifier, scene.device, scene.dtype)
    with torch.no_grad():
        for c in tqdm(range(len(cameras)), desc="group maps", unit="view", leave=False,
                      disable=not progress):
            img, _, _ = scene.render(cameras[c].to(scene.device), identities=True, rgb=False, **raster_kwargs)
            yield torch.softmax(clf(img[0]), dim=-1)


def render_group_maps(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                      progress: bool = False, **raster_kwargs) -> tuple[Tensor, Tensor]:
    """Group maps of ``cameras``.

    The identity channels are rendered (one pass per camera, no RGB), the
    classifier is applied per pixel and a softmax taken. Pixels no Gaussian
    covers render identity 0 and so take the class of the classifier's bias.

    Returns:
        ``labels [C, H, W]`` long in ``0..K-1`` and ``probs [C, H, W, K]`` (on the scene's device).
    """
    probs = list(_iter_group_probs(scene, cameras, classifier, progress=progress, **raster_kwargs))
    probs = torch.stack(probs)
    return probs.argmax(dim=-1), probs


def group_labels(scene: GaussianScene, cameras: Cameras, classifier: torch.nn.Linear, *,
                 progress: bool = False) -> Tensor:
    """``[C, H, W]`` group maps only, kept on the CPU as int16 (memory-light for many large views)."""
    out = [p.argmax(dim=-1).to("cpu", torch.int16)
           for p in _iter_group_probs(scene, cameras, classifier, progress=progress)]
    return torch.stack(out)


def gaussian_groups(scene: GaussianScene, classifier: torch.nn.Linear) -> tuple[Tensor, Tensor]:
    """Classify each Gaussian's own identity vector: ``(ids [N] long, prob [N])`` (the winning probability)."""
    if scene.identities is None:
        raise InputError("scene has no identity encodings: run `ssgwarp group` first")
    clf = _copy_linear(classifier, scene.device, scene.dtype)
    with torch.no_grad():
        p = torch.softmax(clf(scene.identities), dim=-1)
        prob, ids = p.max(dim=-1)
    return ids, prob


def load_groups(scene_dir: str | Path, device=None) -> GroupModel:
    """The classifier of a grouped run (``SCENE_DIR/groups/classifier.pt``) as a :class:`GroupModel`."""
    scene_dir = Path(scene_dir)
    path = scene_dir / "groups" / "classifier.pt"
    if not path.is_file():
        raise InputError(f"{scene_dir}: not grouped (no {path}); run `ssgwarp group {scene_dir}` first")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
        dim, k = int(obj["dim"]), int(obj["num_groups"])
        lin = torch.nn.Linear(dim, k)
        lin.load_state_dict(obj["state_dict"])
    except (KeyError, RuntimeError, ValueError, EOFError) as e:
        raise InputError(f"{path}: not a valid group classifier ({e}); rerun `ssgwarp group --force`") from None
    lin = lin.to(device if device is not None else "cpu").requires_grad_(False)
    info = read_json(scene_dir / "groups" / "groups.json") if (scene_dir / "groups" / "groups.json").is_file() else {}
    return GroupModel(classifier=lin, num_groups=k, dim=dim, info=info)

