"""Where the benchmark scripts find the shared captures (run as ``python benchmarks/<name>.py``, which
puts this folder on ``sys.path``)."""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# beside the repository (the development machines), the GPU machine's copy, a checkout inside the
# repository, the shared copy of a worktree
CANDIDATES = (ROOT.parent / "shared" / "data", Path("/root/data"), ROOT / "shared" / "data", Path("/work/shared/data"))


def data_root() -> Path:
    """The first candidate folder that exists (the first one when none does, for the error message)."""
    return next((p for p in CANDIDATES if p.is_dir()), CANDIDATES[0])


STYLE_SUFFIXES = (".jpg", ".jpeg", ".png")


def style_paths(spec: str, folder: Path) -> list[Path]:
    """The style images named by ``spec`` (comma-separated names without extension, or paths; empty: every
    image in ``folder``, sorted by name); raises ``InputError`` naming what was not found."""
    from ssgwarp.errors import InputError

    folder = Path(folder)
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in STYLE_SUFFIXES) if folder.is_dir() else []
    if not spec:
        if not images:
            raise InputError(f"no style images in {folder}: give the styles or their folder")
        return images
    out = []
    for name in (n.strip() for n in spec.split(",") if n.strip()):
        p = Path(name)
        found = p if p.is_file() else next((q for q in images if q.stem == name), None)
        if found is None:
            raise InputError(f"style {name!r}: not a file and not an image in {folder}")
        out.append(found)
    return out


# the shared captures by short name: (folder under the data root, image sub-folder)
CAPTURES = {"fern8": ("llff_fern", "images_8"), "fern4": ("llff_fern", "images_4"), "cup": ("colmap_cup", "images"),
            "lego": ("lego_200", "images"), "livingroom": ("livingroom_360", "images"),
            "bird": ("bird_360", "images")}


def capture_folder(spec: str, root: Path | None = None) -> tuple[Path, str]:
    """``(folder, image sub-folder)`` of a capture named by ``spec``: a name of :data:`CAPTURES` (under ``root``,
    default :func:`data_root`) or ``PATH[:IMAGES]`` (default ``images``); raises ``InputError`` when the folder
    is missing."""
    from ssgwarp.errors import InputError

    if spec in CAPTURES:
        name, images = CAPTURES[spec]
        folder = Path(root or data_root()) / name
    else:
        path, _, images = spec.partition(":")
        folder, images = Path(path).expanduser(), images or "images"
    if not folder.is_dir():
        raise InputError(f"capture {spec!r}: {folder} is not a folder (shared captures: {', '.join(CAPTURES)}; "
                         "or give PATH[:IMAGES], or --data-root)")
    return folder, images
