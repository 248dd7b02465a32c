"""What the viewer shows, gathered from a run directory: scene, group labels, cameras, key views.

No VTK here: these functions turn files and flags into numpy arrays and
:class:`ssgwarp.core.cameras.Cameras`, with one-line :class:`InputError` messages
for anything a user can get wrong.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np
import torch

from ssgwarp.core.cameras import Cameras
from ssgwarp.errors import InputError, SsgwarpError
from ssgwarp.core.fileio import read_json
from ssgwarp.raster.groups import gaussian_groups, load_groups
from ssgwarp.formats.registry import is_splat_file, read_splat_file
from ssgwarp.raster.scene import GaussianScene
from ssgwarp.services.runs import Run


@dataclass
class GroupInfo:
    """Per-Gaussian group labels.

    Attributes:
        labels: ``[N]`` int64 group id per Gaussian (``-1``: none).
        num_groups: K, the number of palette entries (ids run 0..K-1).
        source: where the labels came from, for the status line and docs.
        prob: ``[N]`` probability of the chosen group, or None when unknown.
    """

    labels: np.ndarray
    num_groups: int
    source: str
    prob: Optional[np.ndarray] = None

    def counts(self) -> np.ndarray:
        """``[K]`` Gaussians per group."""
        lab = self.labels[self.labels >= 0]
        return np.bincount(lab, minlength=self.num_groups)[: self.num_groups]


def resolve_ply(path: str | Path) -> Path:
    """The PLY file for ``path``: the file itself, or ``path/scene.ply`` for a run directory."""
    path = Path(path)
    if path.is_dir():
        cand = path / "scene.ply"
        if not cand.is_file():
            raise InputError(f"{path}: directory has no scene.ply (pass a PLY file or a run directory "
                             "written by `ssgwarp reconstruct`)")
        return cand
    if not path.exists():
        raise InputError(f"{path}: PLY file not found")
    return path


def load_scene(path: str | Path) -> GaussianScene:
    """Read a Gaussian scene: a PLY (INRIA 3DGS layout, ``obj_dc_*`` identities when present) or any other splat
    file (compressed PLY, SPZ, ``.splat``: :func:`ssgwarp.formats.registry.read_splat_file`).

    Raises :class:`InputError` with the file name for anything that is not a
    readable splat file (missing, empty, wrong magic, truncated, missing fields).
    """
    path = resolve_ply(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as e:
        raise InputError(f"{path}: cannot open ({e.strerror})") from None
    if not head:
        raise InputError(f"{path}: file is empty (expected a Gaussian-splat PLY)")
    if head[:3] != b"ply" and is_splat_file(path):
        return read_splat_file(path)
    if head[:3] != b"ply":
        raise InputError(f"{path}: not a PLY file (it does not start with the 'ply' magic line) nor another splat "
                         "file (compressed PLY, SPZ, .splat); pass the scene.ply written by `ssgwarp reconstruct`")
    try:
        return read_splat_file(path)
    except SsgwarpError:
        raise
    except (ValueError, KeyError, IndexError, TypeError, EOFError, OSError, RuntimeError) as e:
        raise InputError(f"{path}: cannot read as a Gaussian-splat PLY ({type(e).__name__}: {e})") from None


def load_labels(path: str | Path, n: int) -> np.ndarray:
    """``[n]`` int64 labels from a ``.npy`` file (or ``.txt``/``.csv`` with one integer per line)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--labels {path}: file not found")
    try:
        arr = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path, ndmin=1)
    except (ValueError, OSError) as e:
        raise InputError(f"--labels {path}: cannot read ({e})") from None
    return check_labels(arr, n, f"--labels {path}")


def check_labels(labels, n: int, what: str = "labels") -> np.ndarray:
    """Validate a per-Gaussian label array: 1-D, length ``n``, integer values >= -1."""
    arr = labels.detach().cpu().numpy() if isinstance(labels, torch.Tensor) else np.asarray(labels)
    arr = arr.reshape(-1) if arr.ndim == 2 and 1 in arr.shape else arr
    if arr.ndim != 1 or len(arr) != n:
        raise InputError(f"{what}: expected one label per Gaussian ({n}), got shape {tuple(arr.shape)}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise InputError(f"{what}: labels must be integers")
    elif arr.dtype.kind not in "iub":
        raise InputError(f"{what}: labels must be integers, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if len(arr) and arr.min() < -1:
        raise InputError(f"{what}: labels must be >= 0 (-1 for 'no group'), got {arr.min()}")
    return arr


def resolve_groups(scene: GaussianScene, *, labels=None, scene_dir: str | Path | None = None,
                   device: torch.device | str = "cpu", num_groups: Optional[int] = None) -> Optional[GroupInfo]:
    """Per-Gaussian group ids, from the best source available.

    Order: ``labels`` given (array, tensor or a path to ``.npy``) → the
    grouping classifier in ``scene_dir/groups/`` applied to the scene's
    identity encodings (``ssgwarp.raster.groups.gaussian_groups``) → the argmax of
    the identity channels (an approximation, said so in ``source``) → None
    (a scene that was never grouped).
    """
    n = len(scene)
    if labels is not None:
        if isinstance(labels, (str, Path)):
            lab, src = load_labels(labels, n), f"labels from {Path(labels).name}"
        else:
            lab, src = check_labels(labels, n), "labels given"
        k = max(int(lab.max()) + 1 if len(lab) else 1, num_groups or 0)
        return GroupInfo(lab, k, src)
    if scene.identities is None:
        return None
    if scene_dir is not None and (Path(scene_dir) / "groups" / "classifier.pt").is_file():
        model = load_groups(scene_dir, device)
        with torch.no_grad():
            ids, prob = gaussian_groups(scene.to(device), model.classifier)
        k = int(getattr(model, "num_groups", 0) or int(ids.max()) + 1)
        return GroupInfo(ids.cpu().numpy().astype(np.int64), k, "grouping classifier",
                         prob.detach().cpu().numpy().astype(np.float32))
    ident = scene.identities.detach().cpu()
    lab = ident.argmax(dim=1).numpy().astype(np.int64)
    prob = torch.softmax(ident.float(), dim=1).max(dim=1).values.numpy()
    return GroupInfo(lab, int(ident.shape[1]) if num_groups is None else num_groups,
                     "argmax of identity channels (no groups/classifier.pt found)", prob)


@dataclass
class RunFolders:
    """Where the viewer finds a run's cameras, groups and key views: the folders holding
    ``cameras.json``, ``groups/classifier.pt`` and ``keyviews/`` (each None when absent)."""

    cameras: Optional[Path] = None
    groups: Optional[Path] = None
    keyviews: Optional[Path] = None


def run_folders(scene_dir: str | Path | None) -> RunFolders:
    """The folders of :class:`RunFolders` for ``scene_dir``: a run folder read by
    :class:`ssgwarp.services.runs.Run` (a stylized run: its source reconstruction's cameras and
    groups, its own key views); a folder that is no run (a bare PLY's): what lies in it."""
    if scene_dir is None:
        return RunFolders()
    d = Path(scene_dir)
    try:
        run = Run.open(d)
    except InputError:
        return RunFolders(d if (d / "cameras.json").is_file() else None,
                          d if (d / "groups" / "classifier.pt").is_file() else None,
                          d / "keyviews" if (d / "keyviews").is_dir() else None)
    groups = run.groups_dir
    return RunFolders(run.camera_dir, None if groups is None else groups.parent,
                      run.keyviews_dir or (d / "keyviews" if (d / "keyviews").is_dir() else None))


def load_cameras(path: str | Path | None, scene_dir: str | Path | None) -> Optional[Cameras]:
    """Cameras from ``path`` (must exist), else ``scene_dir/cameras.json`` when present, else None."""
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise InputError(f"--cameras {p}: file not found")
        return Cameras.load(p)
    if scene_dir is not None and (Path(scene_dir) / "cameras.json").is_file():
        return Cameras.load(Path(scene_dir) / "cameras.json")
    return None


_ID_KEYS = ("camera_ids", "ids", "keyviews", "key_views", "views", "cameras", "camera_names", "names",
            "camera_id", "camera", "camera_name", "id", "name", "index")


def _ids_from_json(obj) -> list:
    """Camera ids (ints) and names (strs) found in a key-view JSON document."""
    if isinstance(obj, bool):
        return []
    if isinstance(obj, (int, str)):
        return [obj]
    if isinstance(obj, list):
        return [x for item in obj for x in _ids_from_json(item)]
    if isinstance(obj, dict):
        for k in _ID_KEYS:
            if k in obj:
                return _ids_from_json(obj[k])
    return []


def _index_of(item, cameras: Cameras, what: str) -> int:
    if isinstance(item, str) and item in cameras.names:
        return cameras.names.index(item)
    try:
        i = int(item)
    except (TypeError, ValueError):
        raise InputError(f"{what}: '{item}' is neither a camera index nor a camera name "
                         f"(names look like '{cameras.names[0]}')") from None
    if not 0 <= i < len(cameras):
        raise InputError(f"{what}: camera index {i} out of range (0..{len(cameras) - 1})")
    return i


def camera_index(item, cameras: Optional[Cameras], what: str = "camera") -> int:
    """Index of a camera given by index or name."""
    if cameras is None:
        raise InputError(f"{what}: no cameras loaded (pass --cameras cameras.json)")
    return _index_of(item, cameras, what)


def resolve_keyviews(items: Iterable, cameras: Optional[Cameras]) -> list[int]:
    """Camera indices of the key views.

    Each item is a camera index, a camera name, a JSON file listing them
    (a list, or an object with e.g. ``camera_ids``/``ids``/``names``; entries
    may be objects with ``camera_id``/``name``), or a key-view directory: its
    JSON files are read the same way, and failing that image file stems that
    equal camera names are taken.
    """
    items = list(items or [])
    if not items:
        return []
    if cameras is None:
        raise InputError("--keyviews: no cameras loaded (pass --cameras cameras.json)")
    out: list[int] = []
    for item in items:
        if isinstance(item, str) and item in cameras.names:
            out.append(cameras.names.index(item))
        elif isinstance(item, (str, Path)) and Path(item).exists():
            out += _keyviews_from_path(Path(item), cameras)
        else:
            out.append(_index_of(item, cameras, "--keyviews"))
    seen: set[int] = set()
    return [i for i in out if not (i in seen or seen.add(i))]


def _keyviews_from_path(p: Path, cameras: Cameras) -> list[int]:
    what = f"--keyviews {p}"
    if p.is_file():
        found = _ids_from_json(read_json(p))
    else:
        found = []
        jsons = sorted(p.glob("*.json"), key=lambda f: (f.name != "keyviews.json", f.name))
        for js in jsons:  # keyviews.json (ssgwarp keyviews) first
            try:
                found = _ids_from_json(read_json(js))
            except InputError:
                continue
            if found:
                break
        if not found:  # no JSON: image files named after their cameras
            names = {n: i for i, n in enumerate(cameras.names)}
            stems = [f.stem for f in sorted(p.rglob("*")) if f.is_file()]
            idx = [names[c] for s in stems for c in {s, s.rsplit("_", 1)[0]} if c in names]
            if idx:
                return idx
    if not found:
        raise InputError(f"{what}: no camera ids or names found in it")
    return [_index_of(x, cameras, what) for x in found]


def finite_mask(scene: GaussianScene) -> np.ndarray:
    """``[N]`` bool: Gaussians whose position, scale and opacity are all finite."""
    ok = torch.isfinite(scene.means).all(dim=1) & torch.isfinite(scene.log_scales).all(dim=1)
    ok &= torch.isfinite(scene.logit_opacities)
    return ok.cpu().numpy()


def as_numpy(t: torch.Tensor | Sequence) -> np.ndarray:
    return t.detach().cpu().double().numpy() if isinstance(t, torch.Tensor) else np.asarray(t, dtype=np.float64)
