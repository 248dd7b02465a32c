"""The run folder: what a stage's output folder holds, how it is read and written, and how a stage claims one.

* :class:`Run` -- a run folder read once: its kind (a ``reconstruction``: ``scene.ply``,
  ``cameras.json``, ``data.json``; or a ``stylized`` run: ``scene.ply`` + ``metrics.json`` naming
  its ``source_scene``), the cameras and their train / test split (by image name in
  ``data.json``), the records (``data.json``, ``metrics.json``), the groups and key views the run
  has (a stylized run: its source's groups), and :meth:`Run.load` -- the scene
  and the capture (:class:`~ssgwarp.capture.datasets.SceneData`, images reloaded from the capture by
  :func:`load_run`, the one reader of ``data.json``);
* :func:`data_json` -- the one writer of ``data.json``; :func:`write_run` -- the one write sequence of a
  reconstruction run (``scene.ply``, ``cameras.json``, ``data.json``, then ``metrics.json`` last: a folder
  with ``metrics.json`` is whole), shared by ``reconstruct``, ``import`` and :func:`write_orbit_run` (a run of
  cameras made around splats, no images); :func:`update_metrics` -- entries added to a run's ``metrics.json``
  (``evaluate``, the from-splats stylize);
* :func:`claim` -- one policy for ``--force`` / ``--resume`` on a stage's outputs: an output
  folder that already holds them is refused unless ``force`` (which removes only what the stage
  writes, :meth:`Claim.clear`) or ``resume`` (which the stage continues from its own record);
  both at once are refused; a path that is a file is refused. A command whose ``--out`` is a folder of its
  own (``render``, ``keyviews``) claims it with :func:`claim_folder`: the same policy, its outputs being
  whatever the folder holds (a non-empty one is refused unless ``force``, which empties it; no resume);
* :func:`resume_record` / :func:`check_resume` -- the one resume record: what a run was started with that
  decides what its checkpoint means (images, resolution, seed, SH degree, strategy, ...). Every command
  that resumes (reconstruct, group, stylize, demo) stores one and checks it: ``--resume`` with another value
  of any of them is refused in one line naming each option and both values; options that only change
  the future (more steps, the checkpoint interval, progress output) are left out of the record;
  :func:`resumed_stages` -- the check for a command that records its finished stages in a JSON file
  (stylize's ``run.json``, the demo's ``demo.json``).

The layout of the files is docs/architecture.md's "Run directories".
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from ..core.cameras import Cameras
from ..capture.datasets import SceneData, load_dataset
from ..capture.loaders import missing_images_error
from ..capture.orbit import orbit_run
from ..errors import InputError, SsgwarpError
from ..core.fileio import read_json, write_json
from ..formats.ply import read_ply, write_ply
from ..raster.scene import GaussianScene

__all__ = ["Run", "RUN_FILES", "data_json", "load_run", "write_run", "write_orbit_run", "update_metrics",
           "Claim", "claim", "claim_folder", "resume_record", "check_resume", "resumed_stages"]

RUN_FILES = ("scene.ply", "cameras.json", "data.json", "metrics.json")   # a reconstruction run's files


def _read_dict(path: Path) -> dict:
    if not path.is_file():
        return {}
    d = read_json(path)
    return d if isinstance(d, dict) else {}


def _path_entry(value: Any, base: Path) -> Optional[Path]:
    """A path recorded in metrics.json (a string or ``{"path": ...}``), relative to ``base`` when not absolute."""
    if isinstance(value, dict):
        value = value.get("path") or value.get("image") or value.get("dir")
    if not value or not isinstance(value, str):
        return None
    p = Path(value).expanduser()
    if not p.is_absolute() and not p.exists():
        p = base / p
    return p


@dataclass
class Run:
    """A run folder (see the module docs). ``recorded``: its ``metrics.json``; ``data``: its
    ``data.json`` (a stylized run: its source's)."""

    path: Path
    kind: str                                  # "reconstruction" | "stylized"
    scene_ply: Path
    source_dir: Optional[Path] = None          # the reconstruction a stylized run came from
    style: Optional[Path] = None
    mode: Optional[str] = None
    recorded: dict = field(default_factory=dict)
    data: dict = field(default_factory=dict)
    _cameras: Optional[Cameras] = field(default=None, repr=False)

    # -- reading ------------------------------------------------------------------------------
    @classmethod
    def open(cls, run_dir: str | Path) -> "Run":
        """Classify a run folder; raises InputError naming what is missing."""
        run = Path(run_dir).expanduser()
        if not run.is_dir():
            raise InputError(f"{run}: run folder not found (run `ssgwarp reconstruct` first)")
        if not (run / "scene.ply").is_file():
            raise InputError(f"{run}: no scene.ply (expected a `ssgwarp reconstruct` or `ssgwarp stylize` output)")
        metrics = _read_dict(run / "metrics.json")
        if "source_scene" in metrics:
            src = _path_entry(metrics["source_scene"], run)
            if src is not None and src.is_file():          # recorded as the source's scene.ply
                src = src.parent
            if src is None or not (src / "cameras.json").is_file():
                raise InputError(f"{run / 'metrics.json'}: source_scene {metrics['source_scene']!r} is not a "
                                 f"reconstruction folder with cameras.json (moved? pass the run again after fixing it)")
            cfg = metrics.get("config")
            mode = metrics.get("mode") or (cfg.get("mode") if isinstance(cfg, dict) else None)
            return cls(run, "stylized", run / "scene.ply", src, _path_entry(metrics.get("style"), run), mode,
                       metrics, _read_dict(src / "data.json"))
        if (run / "cameras.json").is_file():
            return cls(run, "reconstruction", run / "scene.ply", recorded=metrics, data=_read_dict(run / "data.json"))
        raise InputError(f"{run}: neither a reconstruction (needs cameras.json and data.json) nor a stylize output "
                         f"(needs metrics.json with source_scene)")

    @classmethod
    def reconstruction(cls, run_dir: str | Path) -> "Run":
        """A reconstruction run (``scene.ply``, ``cameras.json``, ``data.json``), else InputError."""
        run = Path(run_dir).expanduser()
        if not run.is_dir():
            raise InputError(f"{run}: run folder not found (run `ssgwarp reconstruct` first)")
        for f in ("scene.ply", "cameras.json", "data.json"):
            if not (run / f).is_file():
                if f == "cameras.json" and "source_scene" in _read_dict(run / "metrics.json"):
                    src = cls.open(run).source_dir
                    raise InputError(f"{run}: a stylize output, not a reconstruction run; this command takes its "
                                     f"source reconstruction {src}")
                raise InputError(f"{run}: not a reconstruction run (no {f}); run `ssgwarp reconstruct` first")
        r = cls.open(run)
        if not isinstance(r.data, dict) or "split" not in r.data:
            raise InputError(f"{run / 'data.json'}: unexpected layout (no 'split')")
        return r

    @property
    def camera_dir(self) -> Path:
        """The folder whose ``cameras.json`` / ``data.json`` the run uses (a stylized run: its source's)."""
        return self.source_dir if self.kind == "stylized" else self.path

    @property
    def cameras(self) -> Cameras:
        """The capture's cameras at the training resolution (read once)."""
        if self._cameras is None:
            self._cameras = Cameras.load(self.camera_dir / "cameras.json")
        return self._cameras

    def _ids(self, which: str, strict: bool = True) -> list[int]:
        index: dict[str, int] = {}
        for i, nm in enumerate(self.cameras.names):
            index.setdefault(nm, i)
            index.setdefault(Path(nm).stem, i)
        out = []
        for nm in (self.data.get("split") or {}).get(which) or []:
            i = index.get(str(nm), index.get(Path(str(nm)).stem))
            if i is None:
                raise InputError(f"{self.camera_dir / 'data.json'}: split names image '{nm}' that cameras.json "
                                 f"does not hold")
            out.append(i)
        return out

    @property
    def test_ids(self) -> list[int]:
        """The held-out views (indices into :attr:`cameras`)."""
        return self._ids("test")

    @property
    def train_ids(self) -> list[int]:
        """The training views (all views not held out when the record names none)."""
        train = self._ids("train")
        if not train:
            test = set(self.test_ids)
            train = [i for i in range(len(self.cameras)) if i not in test] or list(range(len(self.cameras)))
        return train

    @property
    def groups_dir(self) -> Optional[Path]:
        """The ``groups/`` folder (``classifier.pt``, ``groups.json``) whose groups the run's Gaussians
        have: its own, else a stylized run's source's (Stage 2 keeps the source's Gaussians and their
        identity encodings); None when neither was grouped."""
        for d in (self.path, self.source_dir):
            if d is not None and (d / "groups" / "classifier.pt").is_file():
                return d / "groups"
        return None

    @property
    def keyviews_dir(self) -> Optional[Path]:
        """A stylized run's ``keyviews/`` folder (``keyviews.json`` naming the key views among
        :attr:`cameras`), else None."""
        d = self.path / "keyviews"
        return d if (d / "keyviews.json").is_file() else None

    @property
    def data_dir(self) -> Optional[Path]:
        """The capture folder the run was made from (as recorded)."""
        d = self.data.get("data_dir")
        return Path(d).expanduser() if d else None

    def background(self, capture: Sequence[float]) -> list[float]:
        """The RGB background the run's scene is shown on: a stylized run's recorded ``background``
        (Stage 2 recolours it with the scene, ``--background transfer``), else ``capture`` (the
        capture's, :attr:`ssgwarp.capture.datasets.SceneData.background`)."""
        bg = self.recorded.get("background") if self.kind == "stylized" else None
        if isinstance(bg, list) and len(bg) >= 3 and all(isinstance(v, (int, float)) for v in bg[:3]):
            return [float(v) for v in bg[:3]]
        return [float(v) for v in capture[:3]]

    def scene(self, device=None):
        """The run's :class:`~ssgwarp.raster.scene.GaussianScene` (from ``scene.ply``)."""
        s = read_ply(self.scene_ply)
        return s if device is None else s.to(device)

    def load(self, device=None, *, data_dir: Optional[str | Path] = None, load_images: bool = True,
             progress: bool = True):
        """``(GaussianScene, SceneData)``: the run's scene and its capture (cameras at the training
        resolution, the split, the images reloaded from the capture unless ``load_images=False``;
        ``data_dir`` overrides the recorded capture folder). A stylized run: its own scene with its
        source's capture. The reading of the records is :func:`load_run`'s."""
        scene, data = load_run(self.camera_dir, device, data_dir=data_dir, load_images=load_images,
                               progress=progress)
        if self.kind == "stylized":
            scene = self.scene(device)
        return scene, data


# ----------------------------------------------------------------------------- reading and writing
def data_json(data: SceneData, **extra) -> dict:
    """The ``data.json`` record of a run trained on ``data``."""
    return {
        "data_dir": str(data.data_dir) if data.data_dir is not None else None,
        "format": data.format,
        "images": data.options.get("images", data.image_dir),
        "width": data.width,
        "height": data.height,
        "split": {"train": [data.names[i] for i in data.train_ids], "test": [data.names[i] for i in data.test_ids]},
        "background": list(data.background),
        "undistorted": data.undistorted,
        "undistortion": data.undistortion,
        "near": data.near,
        "far": data.far,
        "points_source": data.points_source,
        "points_count": None if data.points is None else int(len(data.points[0])),
        "points_reprojection_error_px": data.points_stats.get("median_reprojection_error_px"),
        "points_stats": data.points_stats,
        "masks": data.masks is not None,
        "applied_transform": data.applied_transform,
        "load_options": data.options,
        **extra,
    }


def load_run(scene_dir: str | Path, device=None, *, data_dir: Optional[str | Path] = None,
             load_images: bool = True, progress: bool = True):
    """Read a reconstruction run: ``(GaussianScene, SceneData)``.

    The scene comes from ``scene.ply``, the cameras from ``cameras.json`` (training
    resolution) and the split and data options from ``data.json``; the images are
    reloaded from the capture (``data_dir`` overrides the recorded folder, e.g. after
    moving it). With ``load_images=False`` the images are left black (cameras only); ``progress``: the
    loading bar of many images.
    """
    scene_dir = Path(scene_dir).expanduser()
    if not scene_dir.is_dir():
        raise InputError(f"{scene_dir}: run folder not found")
    for f in ("scene.ply", "cameras.json", "data.json"):
        if not (scene_dir / f).is_file():
            raise InputError(f"{scene_dir}: not a reconstruction run (no {f}); run `ssgwarp reconstruct` first")
    scene = read_ply(scene_dir / "scene.ply")
    cams = Cameras.load(scene_dir / "cameras.json")
    meta = read_json(scene_dir / "data.json")
    if not isinstance(meta, dict) or "split" not in meta:
        raise InputError(f"{scene_dir / 'data.json'}: unexpected layout (no 'split')")
    split = meta["split"]
    index = {n: i for i, n in enumerate(cams.names)}
    unknown = [n for n in list(split.get("train", [])) + list(split.get("test", [])) if n not in index]
    if unknown:
        raise InputError(f"{scene_dir / 'data.json'}: split names not in cameras.json: {', '.join(unknown[:5])}")
    train = [index[n] for n in split.get("train", [])]
    test = [index[n] for n in split.get("test", [])]
    bg = tuple(float(v) for v in meta.get("background", (1.0, 1.0, 1.0)))
    src = data_dir or meta.get("data_dir")
    points = masks = None
    images = torch.zeros(len(cams), cams.height, cams.width, 3)
    data_root = Path(src).expanduser() if src else None
    undistortion = meta.get("undistortion")
    if load_images:
        if data_root is None or not data_root.is_dir():
            raise InputError(f"{scene_dir / 'data.json'}: capture folder {src} not found "
                             f"(pass data_dir= / --data-dir to say where it is now)")
        opts = dict(meta.get("load_options", {}))
        opts.pop("split_every", None)
        opts["width"] = cams.width
        # the capture's own points at most: a run's initial points are not made again
        data = load_dataset(data_root, init="capture", **{k: opts[k] for k in ("images", "background", "width",
                                                                               "max_images", "num_random_points",
                                                                               "seed", "format") if k in opts},
                            progress=progress)
        pos = {n: i for i, n in enumerate(data.names)}
        missing = [n for n in cams.names if n not in pos]
        if missing:
            raise missing_images_error(missing, data_root, f"{scene_dir / 'cameras.json'}")
        sel = [pos[n] for n in cams.names]
        images = data.images[sel]
        if (data.width, data.height) != (cams.width, cams.height) or not torch.allclose(
                data.cameras.Ks[sel].double(), cams.Ks.double(), rtol=0.0, atol=1e-2):
            raise InputError(f"{data_root} now loads as {data.width}x{data.height} images with other intrinsics "
                             f"than the run's {scene_dir / 'cameras.json'} ({cams.width}x{cams.height}): the run was "
                             f"made from other data or by an ssgwarp that did not crop undistorted images; run "
                             f"`ssgwarp reconstruct` again")
        points, undistortion = data.points, data.undistortion
        if data.points_source != meta.get("points_source"):
            points = None  # triangulated or given points are not remade
        masks = None if data.masks is None else data.masks[sel]
    out = SceneData(cameras=cams, images=images, names=list(cams.names), train_ids=train, test_ids=test,
                    points=points, points_source=meta.get("points_source", "none"), near=meta.get("near"),
                    far=meta.get("far"), background=bg, data_dir=data_root, image_dir=meta.get("images"),
                    format=meta.get("format", ""), undistortion=undistortion, options=meta.get("load_options", {}),
                    masks=masks, applied_transform=meta.get("applied_transform"))
    if device is not None:
        scene, out = scene.to(device), out.to(device)
    return scene, out


def write_run(out: str | Path, scene: GaussianScene, data: SceneData, metrics: Optional[dict] = None, *,
              record: Optional[dict] = None, finish: Optional[Callable[[], Optional[dict]]] = None) -> None:
    """Write the reconstruction run ``out`` (created): ``scene.ply`` (on the CPU), ``cameras.json`` (the
    capture's cameras at the training resolution), ``data.json`` (:func:`data_json` of ``data`` with
    ``record``'s entries), then ``finish()`` (what the run files are needed for; the dict it returns joins
    ``metrics``) and ``metrics.json`` last (None: none written, the caller writes it)."""
    out = Path(out).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    write_ply(out / "scene.ply", scene.detach().to("cpu"))
    data.cameras.to("cpu").save(out / "cameras.json")
    write_json(out / "data.json", data_json(data, **(record or {})))
    if finish is not None:
        extra = finish() or {}
        if metrics is not None:
            metrics.update(extra)
    if metrics is not None:
        write_json(out / "metrics.json", metrics)


def write_orbit_run(scene: GaussianScene, out: str | Path, *, source: str | Path, views: int = 24,
                    max_width: int = 512, width: Optional[int] = None, up: Optional[np.ndarray] = None,
                    background: Sequence[float] = (1.0, 1.0, 1.0), seed: int = 0) -> dict:
    """Write ``out`` as a reconstruction run of ``scene`` with ``views`` cameras made around it
    (:func:`ssgwarp.capture.orbit.orbit_run`; all of them training views: there are no images to hold out),
    no ``metrics.json``; returns the ``orbit`` record written to ``data.json``."""
    data, record = orbit_run(scene, source=source, views=views, max_width=max_width, width=width, up=up,
                             background=background, seed=seed)
    write_run(out, scene, data, record={"orbit": record})
    return record


def update_metrics(run_dir: str | Path, entries: dict) -> dict:
    """Add ``entries`` to ``run_dir/metrics.json`` (made when absent; written atomically); returns the whole."""
    path = Path(run_dir) / "metrics.json"
    merged = _read_dict(path)
    merged.update(entries)
    write_json(path, merged)
    return merged


# ----------------------------------------------------------------------------- claiming outputs
@dataclass
class Claim:
    """A stage's claim on its outputs in ``path``: ``existing`` (those already there), ``resume``."""

    path: Path
    outputs: tuple[str, ...]
    existing: list[str]
    force: bool
    resume: bool
    scratch: tuple[str, ...] = ()

    def clear(self) -> None:
        """With ``force``: remove the stage's existing outputs and scratch files (only those; other
        files stay)."""
        if not self.force:
            return
        for f in [*self.existing, *(s for s in self.scratch if (self.path / s).exists())]:
            p = self.path / f
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
        self.existing = []


def claim(out: str | Path, outputs: Sequence[str], *, force: bool = False, resume: bool = False,
          what: str = "outputs", resumable: bool = True, clear: bool = False, scratch: Sequence[str] = ()) -> Claim:
    """Check that ``out`` may receive a stage's ``outputs`` (names relative to it).

    Refuses (one line, naming the fix): ``force`` with ``resume``; ``out`` a file; outputs
    already there without ``force`` or ``resume`` ("OUT already holds WHAT (...); pass --force
    ..."). ``clear``: remove them at once under ``force`` (else call :meth:`Claim.clear` when
    everything else has been validated). ``scratch``: work files (partial results) that ``force``
    removes too but that alone do not make ``out`` taken. The stage continues from its own record
    on ``resume``."""
    out = Path(out).expanduser()
    if force and resume:
        raise InputError("--resume and --force exclude each other")
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    existing = [f for f in outputs if (out / f).exists()]
    if existing and not (force or resume):
        hint = " or --resume to continue it" if resumable else ""
        raise SsgwarpError(f"{out} already holds {what} ({', '.join(existing)}); pass --force to overwrite it{hint}")
    c = Claim(out, tuple(outputs), existing, bool(force), bool(resume), tuple(scratch))
    if clear:
        c.clear()
    return c


def claim_folder(path: str | Path, force: bool) -> Path:
    """Claim ``path`` for a command whose outputs fill a folder of their own (``render --out``, ``keyviews
    --out``): :func:`claim`'s policy with everything the folder holds as its outputs (refused unless
    ``force``, which empties it; no resume). A file there is refused unless ``force`` (which removes it).
    Returns the folder, created."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        if not force:
            raise InputError(f"{path}: exists and is not a folder; pass --force to overwrite it")
        path.unlink()
    held = sorted(p.name for p in path.iterdir()) if path.is_dir() else []
    if held and not force:     # (a render's hundreds of frames: the first few named)
        raise SsgwarpError(f"{path} already holds files ({', '.join(held[:3])}{', ...' if len(held) > 3 else ''}); "
                           f"pass --force to overwrite it")
    claim(path, held, force=force, what="files", resumable=False, clear=True)
    path.mkdir(parents=True, exist_ok=True)
    return path


# ----------------------------------------------------------------------------- the resume record
NOT_RECORDED = "(not recorded)"


def resume_record(**options: Any) -> dict:
    """The resume record of a run: ``options`` (keyed by their command-line spelling, e.g. ``"--width"``,
    or a plain name for what is not an option, e.g. ``"resolution"``) as they read back from JSON (tuples
    become lists, paths strings), so that a record stored in a checkpoint or a JSON file compares equal to
    a fresh one of the same options."""
    import json

    return json.loads(json.dumps(options, default=str))


def resume_changes(old: dict, new: dict) -> list[str]:
    """``"--width 252 -> 200"`` for each entry of ``new`` that differs from ``old`` (a dict value, e.g. a
    stage's whole configuration, is compared field by field: ``"stage2.lr 0.1 -> 0.5"``); an entry the
    earlier run did not record reads ``(not recorded)``."""
    def show(v: Any) -> str:
        text = NOT_RECORDED if v is _MISSING else ("none" if v is None else str(v))
        return text if len(text) <= 60 else text[:57] + "..."     # (a list of image names: its start)

    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, _MISSING), new.get(k, _MISSING)
        if k not in new:
            continue                      # (what this version no longer records does not block a resume)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{k}.{f} {show(a.get(f, _MISSING))} -> {show(b.get(f, _MISSING))}"
                    for f in sorted(set(a) | set(b)) if a.get(f, _MISSING) != b.get(f, _MISSING)]
        elif a != b:
            out.append(f"{k} {show(a)} -> {show(b)}")
    return out


_MISSING = object()


def resumed_stages(claimed: Claim, record_file: str, key: str, new: dict, what: str, *, kind: str,
                   fmt: Optional[str] = None, required: bool = False) -> dict:
    """The finished stages of a command that records its stages in ``claimed.path / record_file`` (JSON:
    ``key``: its resume record, ``stages``; ``fmt``: its ``format`` when it has one): on a ``--resume`` of a
    folder that holds outputs, the record's ``stages`` once :func:`check_resume` has compared ``key`` with
    ``new`` (``what``: the earlier run, as the refusal names it); else ``{}``. No record: ``{}``, or with
    ``required`` "nothing to resume"; a file that is not one (``kind``, e.g. "a demo record"): refused."""
    path = claimed.path / record_file
    if not (claimed.existing and claimed.resume):
        return {}
    if not path.is_file():
        if required:
            raise InputError(f"{claimed.path}: nothing to resume (no {record_file}); pass --force to start over")
        return {}
    old = read_json(path)
    if not isinstance(old, dict) or (fmt is not None and old.get("format") != fmt):
        raise InputError(f"{path}: not {kind}; pass --force to start over")
    rec = old.get(key)
    check_resume(rec if isinstance(rec, dict) else {key: rec}, new, claimed.path, what)
    return dict(old.get("stages", {}))


def check_resume(old: Optional[dict], new: dict, where: str | Path, what: str = "the run") -> None:
    """Refuse a ``--resume`` whose options (``new``, a :func:`resume_record`) differ from those ``what`` was
    started with (``old``; None: a record written before records existed, not checked): one line naming
    ``where``, each differing option and both values (``before -> now``)."""
    if old is None:
        return
    changed = resume_changes(old, new)
    if changed:
        raise InputError(f"{where}: --resume with other options than {what} was started with "
                         f"({'; '.join(changed)}); pass the same ones, or --force to start over")
