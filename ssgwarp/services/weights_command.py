"""``ssgwarp weights``: the table of pretrained models (where each is found, size, licence, users; hashes
checked with ``--verify``) and ``--download`` (:func:`ssgwarp.services.weights.fetch`). Finding and fetching
are :mod:`ssgwarp.services.weights`; this is the command and its table.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping, Optional

from .weight_specs import SPECS, WeightSpec, _git_blob_sha1, _sha256, _spec
from .weights import _human, _inside, hub_cache, locate, offline_reason, torch_checkpoints

__all__ = ["status", "verify", "table"]


def _snapshot_of(spec: WeightSpec, path: Path) -> Optional[Path]:
    """The snapshot folder holding ``path`` when it is ``spec``'s entry in the Hugging Face cache."""
    if not (spec.repo and _inside(path, hub_cache())):
        return None
    inner = spec.filename if not spec.is_dir else spec.subfolder
    for _ in Path(inner).parts if inner else ():
        path = path.parent
    return path


def _files_of(spec: WeightSpec, path: Path) -> dict[str, Path]:
    """``{name: file}`` of the weights at ``path`` (the spec's files in a cache snapshot, else every file)."""
    snap = _snapshot_of(spec, path)
    if snap is not None:
        out = {}
        for entry in spec.patterns or spec.files:
            for pat in entry.split("|"):
                out.update({str(q.relative_to(snap)): q for q in snap.glob(pat) if q.is_file()})
        return out
    if path.is_file():
        return {path.name: path}
    return {str(q.relative_to(path)): q for q in path.rglob("*") if q.is_file()}


def _disk_size(spec: WeightSpec, path: Path) -> int:
    return sum(os.path.getsize(f) for f in _files_of(spec, path).values())


def status(key: str, explicit: Optional[str | os.PathLike] = None,
           config: Optional[Mapping[str, str]] = None) -> dict:
    """``{"model", "found", "route", "path", "bytes", "size", "licence", "used_by", "missing"}`` for ``key``."""
    spec = _spec(key)
    got = locate(key, explicit, config)
    row = {"model": key, "found": got is not None, "route": got[1] if got else None,
           "path": str(got[0]) if got else None, "licence": spec.licence, "used_by": spec.used_by,
           "missing": [r for r in spec.required if got and not (got[0] / r).exists()]}
    if got:
        row["bytes"] = _disk_size(spec, got[0])
        row["size"] = _human(row["bytes"])
    else:
        row["bytes"] = None
        row["size"] = f"~{_human(spec.size)}"
    return row


def verify(key: str, path: str | os.PathLike) -> tuple[Optional[bool], str]:
    """Check the files of ``key`` at ``path`` against their published hashes.

    Hugging Face cache files against the blob they link to (SHA-256 for large
    files, the git object hash for small ones); single files with a published
    hash (torchvision, LPIPS) against it. ``(True|False|None, note)``; None:
    nothing to check against (e.g. a folder outside the cache).
    """
    spec = _spec(key)
    path = Path(path)
    if spec.sha256 and path.is_file():
        ok = _sha256(path).startswith(spec.sha256)
        return ok, "SHA-256 matches" if ok else f"SHA-256 differs from the published {spec.sha256[:12]}..."
    if _snapshot_of(spec, path) is not None:
        bad, checked = [], 0
        for name, f in _files_of(spec, path).items():
            if not f.is_symlink():      # copied instead of linked (no symlinks on this file system)
                continue
            blob = Path(os.path.realpath(f))
            digest = {64: _sha256, 40: _git_blob_sha1}.get(len(blob.name))
            if digest is None:
                continue
            checked += 1
            if not blob.is_file() or digest(blob) != blob.name:
                bad.append(name)
        if bad:
            return False, f"hash mismatch: {', '.join(bad)}"
        return (True, f"{checked} files match their hub hashes") if checked else (None, "no hashed files")
    return None, "no published hash to check against"


def table(keys: Optional[Iterable[str]] = None, config: Optional[Mapping[str, str]] = None,
          check: bool = False) -> str:
    """The text table of ``ssgwarp weights``: model, where found (or missing), size, licence, used by."""
    rows = []
    for key in keys or SPECS:
        s = status(key, config=config)
        where = f"{s['route']}: {s['path']}" if s["found"] else f"missing (ssgwarp weights --download {key})"
        if s["missing"]:
            where += f" [lacks {', '.join(s['missing'])}]"
        row = [key, where, s["size"], s["licence"], s["used_by"]]
        if check:
            ok, note = verify(key, s["path"]) if s["found"] else (None, "")
            row.append({True: "ok", False: "BAD", None: "-"}[ok] + (f" ({note})" if ok is False else ""))
        rows.append(row)
    head = ["model", "found in", "size", "licence", "used by"] + (["check"] if check else [])
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    lines = [fmt.format(*head).rstrip(), fmt.format(*["-" * w for w in widths])]
    lines += [fmt.format(*r).rstrip() for r in rows]
    off = offline_reason()
    lines.append(f"Hugging Face cache: {hub_cache()}; torch hub checkpoints: {torch_checkpoints()}; "
                 f"downloads {'off (' + off + ')' if off else 'on first use'}")
    return "\n".join(lines)
