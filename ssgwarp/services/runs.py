"""The run folder: what a stage's output folder holds, and how a stage claims one.

* :class:`Run` -- a run folder read once: its kind (a ``reconstruction``: ``scene.ply``,
  ``cameras.json``, ``data.json``; or a ``stylized`` run: ``scene.ply`` + ``metrics.json`` naming
  its ``source_scene``), the cameras and their train / test split (by image name in
  ``data.json``), the records (``data.json``, ``metrics.json``), the groups and key views the run
  has (a stylized run: its source's groups), and :meth:`Run.load` -- the scene
  and the capture (:class:`~ssgwarp.capture.datasets.SceneData`, images reloaded from the capture by
  :func:`ssgwarp.capture.datasets.load_run`, the one reader of ``data.json``, as ``data_json`` its writer);
* :func:`claim` -- one policy for ``--force`` / ``--resume`` on a stage's outputs: an output
  folder that already holds them is refused unless ``force`` (which removes only what the stage
  writes, :meth:`Claim.clear`) or ``resume`` (which the stage continues from its own record);
  both at once are refused; a path that is a file is refused; :func:`claim_folder` -- the same policy for
  a command whose ``--out`` is a folder of its own (``render``, ``keyviews``): a non-empty one is refused
  unless ``force``, which empties it;
* :func:`resume_record` / :func:`check_resume` -- the one resume record: what a run was started with that
  decides what its checkpoint means (images, resolution, seed, SH degree, strategy, ...). Every command
  that resumes (reconstruct, group, stylize, demo) stores one and checks it: ``--resume`` with another value
  of any of them is refused in one line naming each option and both values; options that only change
  the future (more steps, the checkpoint interval, progress output) are left out of the record.

The layout of the files is docs/architecture.md's "Run directories".
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Sequence


from ..core.cameras import Cameras
from ..capture.datasets import load_run
from ..errors import InputError, SsgwarpError
from ..core.fileio import read_json
from ..formats.ply import read_ply

__all__ = ["Run", "Claim", "claim", "claim_folder", "resume_record", "check_resume"]


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
        source's capture. The reading of the records is :func:`ssgwarp.capture.datasets.load_run`'s."""
        scene, data = load_run(self.camera_dir, device, data_dir=data_dir, load_images=load_images,
                               progress=progress)
        if self.kind == "stylized":
            scene = self.scene(device)
        return scene, data


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
    """Make ``path`` ready for a command whose outputs fill a folder of their own (``render --out``,
    ``keyviews --out``): an existing non-empty folder (or a file) is refused unless ``force`` (then it is
    emptied), so outputs are never overwritten by accident. Returns the folder, created."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        if not force:
            raise InputError(f"{path}: already exists and is not empty; pass --force to overwrite it")
        shutil.rmtree(path) if path.is_dir() else path.unlink()
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
