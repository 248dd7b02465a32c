"""Pretrained weights: where they are on this machine, and fetching them the way the ecosystem does.

Each model (``SPECS``) is looked for, in order, at:

1. an explicit path (a CLI flag / API argument) — when given, only there;
2. the config mapping (``--config FILE``, key ``weights``);
3. its environment variable (``SSGWARP_SD15``, ``SSGWARP_VGG16``, ...);
4. ``$SSGWARP_WEIGHTS/<default name>``;
5. the ecosystem's cache: the Hugging Face Hub cache (``HF_HUB_CACHE``, else
   ``$HF_HOME/hub``, else ``~/.cache/huggingface/hub``; layout
   ``models--ORG--NAME/snapshots/REV/...`` with ``refs/main``), read through
   ``huggingface_hub.try_to_load_from_cache``, for the diffusers / transformers
   models; the torch hub checkpoints folder (``torch.hub.get_dir()/checkpoints``,
   ``$TORCH_HOME/hub/checkpoints``) for the torchvision weights files of VGG16
   and RAFT; the installed ``lpips`` package for the LPIPS heads;
6. a download on first use, into that cache, through the library that owns it
   (``huggingface_hub.snapshot_download``, ``torch.hub.download_url_to_file``
   with the published SHA-256 checked), after one line saying what, from where,
   how large (the hub's metadata, or the spec's approximate size) and under
   which licence — unless downloads are off: ``--offline``, ``SSGWARP_OFFLINE=1``,
   ``HF_HUB_OFFLINE=1`` or ``TRANSFORMERS_OFFLINE=1``, or an earlier download in
   this process found no network (one probe per process, :func:`probe`, with short timeouts:
   ``SSGWARP_DOWNLOAD_TIMEOUT`` seconds, default 10; its answer is kept).

Both libraries write a download under a temporary name in the destination folder
and move it in place when complete, so an interrupted or failed download leaves
nothing half-written.

:func:`find` never downloads (None when absent); :func:`require` may download and
raises :class:`~ssgwarp.errors.WeightsNotFound` with a short one-line message (what is
missing, its size, ``ssgwarp weights --download NAME``; the long form with every
explicit-path alternative under ``--debug`` (:func:`verbose`) and in ``ssgwarp weights``);
:func:`notice` prints such a line once per model and command where a stage runs without them;
:func:`load_error` turns a truncated or corrupt file into a one-line error
naming the file and how to fetch it again. ``ssgwarp weights`` prints the table
(:func:`table`) and ``ssgwarp weights --download [NAMES]`` fetches (:func:`fetch`).
"""
from __future__ import annotations

import argparse
import contextlib
import fnmatch
import importlib.util
import os
import socket
import sys
from pathlib import Path
from typing import Iterable, Iterator, Mapping, Optional

from ..errors import InputError, SsgwarpError, WeightsNotFound
from .weight_specs import (  # noqa: F401 (re-exported: part of this module's API)
    GROUPS, SPECS, WeightSpec, _git_blob_sha1, _sha256, _spec)

__all__ = ["WeightSpec", "SPECS", "GROUPS", "DownloadFailed", "find", "locate", "require", "obtain", "fetch",
           "message", "notice", "load_error", "offline_reason", "offline", "verbose", "probe", "hub_cache",
           "torch_checkpoints",
           "status", "table", "verify", "add_arguments", "run"]


class DownloadFailed(WeightsNotFound):
    """A model was missing and downloading it failed (no network, refused, wrong hash)."""


_TRUE = ("1", "true", "yes", "on")
_OFFLINE_FLAG: Optional[str] = None          # set by --offline (offline())
_NETWORK_DOWN: Optional[str] = None          # reason, once a download found no network in this process
_NETWORK_OK: Optional[bool] = None           # True once the probe reached the network (kept for the process)
_VERBOSE: bool = False                       # --debug: messages in their long form
_SAID: set = set()                           # models whose absence this command has reported (notice())


# -- where the ecosystem keeps its files -----------------------------------------------------------
def hub_cache() -> Path:
    """The Hugging Face Hub cache folder, from the environment at call time (as ``huggingface_hub`` does)."""
    for var in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"):
        if os.environ.get(var):
            return Path(os.path.expandvars(os.path.expanduser(os.environ[var])))
    home = os.environ.get("HF_HOME") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "huggingface")
    return Path(os.path.expandvars(os.path.expanduser(home))) / "hub"


def torch_checkpoints() -> Path:
    """``torch.hub.get_dir()/checkpoints`` (``$TORCH_HOME/hub/checkpoints``), where torchvision keeps weights."""
    import torch.hub

    return Path(torch.hub.get_dir()) / "checkpoints"


def _hf():
    try:
        import huggingface_hub
    except ImportError:
        return None
    return huggingface_hub


def _lpips_package_file() -> Optional[Path]:
    """``weights/v0.1/vgg.pth`` of an installed ``lpips`` package (found without importing it)."""
    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        return None
    for loc in (spec.submodule_search_locations or []) if spec else []:
        p = Path(loc) / "weights" / "v0.1" / "vgg.pth"
        if p.is_file():
            return p
    return None


def _hub_snapshot(spec: WeightSpec) -> Optional[Path]:
    """The cached snapshot folder of ``spec.repo`` (refs/main) when every file of ``spec.files`` is in it."""
    hf = _hf()
    if hf is None or not spec.repo:
        return None
    snapshot = None
    for entry in spec.files:
        for f in entry.split("|"):
            try:
                got = hf.try_to_load_from_cache(spec.repo, f, cache_dir=str(hub_cache()))
            except Exception:     # a malformed cache entry: treat as absent
                got = None
            if isinstance(got, str):
                break
        else:
            return None
        root = Path(got)
        for _ in Path(f).parts:
            root = root.parent
        snapshot = snapshot or root
    return snapshot


def _cache_path(spec: WeightSpec) -> Optional[tuple[Path, str]]:
    """``(path, route)`` of ``spec`` in the ecosystem's caches, or None."""
    if spec.repo:
        snap = _hub_snapshot(spec)
        if snap is not None:
            inner = spec.filename if not spec.is_dir else spec.subfolder
            return (snap / inner if inner else snap), "Hugging Face cache"
        return None
    if spec.key == "lpips":
        p = _lpips_package_file()
        if p is not None:
            return p, "lpips package"
    if spec.url and spec.filename:
        p = torch_checkpoints() / spec.filename
        if p.is_file():
            return p, "torch hub cache"
    return None


# -- finding -----------------------------------------------------------------------------------------
def locate(key: str, explicit: Optional[str | os.PathLike] = None,
           config: Optional[Mapping[str, str]] = None) -> Optional[tuple[Path, str]]:
    """``(path, route)`` of weights ``key`` on this machine, or None (never downloads).

    ``route`` names where it was found: ``explicit``, ``config``, the environment
    variable, ``$SSGWARP_WEIGHTS``, ``Hugging Face cache``, ``torch hub cache`` or
    ``lpips package``. An explicit path is the only candidate when given.
    """
    spec = _spec(key)
    ok = (lambda p: p.is_dir()) if spec.is_dir else (lambda p: p.is_file())
    if explicit:
        p = Path(explicit).expanduser()
        return (p, "explicit") if ok(p) else None
    candidates: list[tuple[Path, str]] = []
    if config and config.get(key):
        candidates.append((Path(config[key]), "config"))
    if os.environ.get(spec.env):
        candidates.append((Path(os.environ[spec.env]), f"${spec.env}"))
    if os.environ.get("SSGWARP_WEIGHTS"):
        candidates.append((Path(os.environ["SSGWARP_WEIGHTS"]) / spec.default, "$SSGWARP_WEIGHTS"))
    for p, route in candidates:
        p = p.expanduser()
        if ok(p):
            return p, route
    return _cache_path(spec)


def find(key: str, explicit: Optional[str | os.PathLike] = None,
         config: Optional[Mapping[str, str]] = None) -> Optional[Path]:
    """The local path of weights ``key`` if present (any route of the module docs), else None. Never downloads."""
    got = locate(key, explicit, config)
    return None if got is None else got[0]


# -- downloads allowed? --------------------------------------------------------------------------------
@contextlib.contextmanager
def offline(reason: str = "--offline") -> Iterator[None]:
    """Downloads off inside the block (``reason`` is what messages say); also a function decorator."""
    global _OFFLINE_FLAG
    old = _OFFLINE_FLAG
    _OFFLINE_FLAG = old or reason
    try:
        yield
    finally:
        _OFFLINE_FLAG = old


@contextlib.contextmanager
def verbose(on: bool = True) -> Iterator[None]:
    """Messages about missing weights in their long form inside the block (``--debug``)."""
    global _VERBOSE
    old = _VERBOSE
    _VERBOSE = bool(on) or old
    try:
        yield
    finally:
        _VERBOSE = old


def offline_reason() -> Optional[str]:
    """Why downloads are off now (``--offline``, ``HF_HUB_OFFLINE=1``, ...), or None when they are allowed."""
    if _OFFLINE_FLAG:
        return _OFFLINE_FLAG
    for var in ("SSGWARP_OFFLINE", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        if os.environ.get(var, "").strip().lower() in _TRUE:
            return f"{var}={os.environ[var]}"
    if _NETWORK_DOWN:
        return f"no network ({_NETWORK_DOWN})" if _VERBOSE else "no network"
    return None


def _connect(host: str, port: int, timeout: float) -> None:
    """Open and close one TCP connection (the network probe; tests replace it)."""
    socket.create_connection((host, port), timeout=timeout).close()


def probe(url: str) -> Optional[str]:
    """Whether the network is reachable: None when it is, else why not.

    One TCP connection to ``url``'s host, with the download timeout, the first time
    a download is wanted in this process; the answer is kept, so a process without
    network waits on it once, and later models are reported missing at once.
    """
    global _NETWORK_DOWN, _NETWORK_OK
    if _NETWORK_DOWN:
        return offline_reason()
    if _NETWORK_OK:
        return None
    from urllib.parse import urlparse

    host = urlparse(url if "://" in url else "https://" + url).hostname or url
    try:
        _connect(host, 443, _timeout())
    except OSError as e:
        _NETWORK_DOWN = f"{host} unreachable: {' '.join(str(e).split())[:200] or type(e).__name__}"
        return offline_reason()
    _NETWORK_OK = True
    return None


def _timeout() -> float:
    try:
        return max(1.0, float(os.environ.get("SSGWARP_DOWNLOAD_TIMEOUT", "10")))
    except ValueError:
        return 10.0


def _human(n: Optional[float]) -> str:
    if n is None:
        return "?"
    for unit, f in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.3g} {unit}" if n / f < 100 else f"{n / f:.0f} {unit}"
    return f"{int(n)} B"


def _where_to(spec: WeightSpec) -> str:
    if spec.repo:
        return f"the Hugging Face cache ({hub_cache()})"
    return f"the torch hub checkpoints folder ({torch_checkpoints()})"


def _alternatives(spec: WeightSpec) -> str:
    flags = f"pass its path ({spec.flags}), " if spec.flags else "pass its path, "
    return (f"{flags}set {spec.env}, or put it at $SSGWARP_WEIGHTS/{spec.default}; "
            f"expected: {spec.expected} (from '{spec.source}')")


def message(key: str, explicit: Optional[str | os.PathLike] = None, reason: Optional[str] = None,
            long: Optional[bool] = None) -> str:
    """One line: weights ``key`` are missing, why none was downloaded, how to fetch them.

    Short by default (what, its download size, ``ssgwarp weights --download KEY``);
    ``long`` (default: under ``--debug``, :func:`verbose`) adds every other way to provide them.
    """
    spec = _spec(key)
    long = _VERBOSE if long is None else long
    if explicit:
        return (f"{explicit} does not exist; no local weights for {key} ({spec.title}): expected {spec.expected}; "
                f"fix the path, or drop it to use {spec.env} / $SSGWARP_WEIGHTS / the cache "
                f"(`ssgwarp weights --download {key}` fetches '{spec.source}')")
    why = f" ({reason})" if reason else ""
    if not long:
        cost = f"~{_human(spec.size)}, " if spec.size else ""
        how = (f"`ssgwarp weights --download {key}` fetches it" if spec.repo or spec.url
               else f"set {spec.env}")
        return f"no local {key} weights{why}: {how} ({cost}`ssgwarp weights` shows where they are looked for)"
    if spec.repo or spec.url:
        fetch_ = (f"run `ssgwarp weights --download {key}` on a machine with network (fetches '{spec.source}', "
                  f"~{_human(spec.size)}, into {_where_to(spec)}), or ")
    else:
        fetch_ = ""
    return f"no local weights for {key} ({spec.title}){why}: {fetch_}{_alternatives(spec)}"


def notice(key: str, text: str, instead: str = "") -> None:
    """Print ``ssgwarp: TEXT; INSTEAD`` on stderr, once per model ``key`` and command (later calls are silent)."""
    if key in _SAID:
        return
    _SAID.add(key)
    print(f"ssgwarp: {text}{'; ' + instead if instead else ''}", file=sys.stderr, flush=True)


def load_error(key: str, path: str | os.PathLike, err: BaseException, what: Optional[str] = None) -> InputError:
    """The error for weights that exist but cannot be read (truncated / corrupt / wrong file), as one line."""
    spec = _spec(key)
    detail = " ".join(str(err).split()) or type(err).__name__
    p = Path(path)
    in_cache = any(_inside(p, root) for root in _cache_roots())
    again = (f"fetch it again with `ssgwarp weights --download {key} --force`" if in_cache else
             f"replace it with {spec.expected}, or remove this path to use the cached copy "
             f"(`ssgwarp weights --download {key}`)")
    return InputError(f"{path}: cannot load {what or spec.title} ({detail[:300]}): the file is truncated, corrupt "
                      f"or not {spec.source}; {again}")


def _cache_roots() -> list[Path]:
    roots = [hub_cache()]
    with contextlib.suppress(Exception):
        roots.append(torch_checkpoints())
    return roots


def _inside(p: Path, root: Path) -> bool:
    try:
        p.absolute().relative_to(root.absolute())
        return True
    except ValueError:
        return False


# -- fetching ------------------------------------------------------------------------------------------
def _hub_files(spec: WeightSpec) -> dict[str, int]:
    """``{path: bytes}`` of the files in ``spec.repo`` (the hub's metadata; raises when unreachable)."""
    info = _hf().HfApi().model_info(spec.repo, files_metadata=True, timeout=_timeout())
    return {s.rfilename: int(s.size or 0) for s in (info.siblings or [])}


def _patterns(spec: WeightSpec, listing: Optional[Mapping[str, int]]) -> list[str]:
    """What to download: each entry of ``spec.patterns`` (default ``files``), ``a|b`` resolved to the first
    alternative the repo has (the first one when its listing is unknown)."""
    out = []
    for entry in spec.patterns or spec.files:
        alts = entry.split("|")
        out.append(next((a for a in alts if listing and a in listing), alts[0]))
    return out


def _download_size(spec: WeightSpec, listing: Mapping[str, int]) -> Optional[int]:
    pats = _patterns(spec, listing)
    sizes = [n for f, n in listing.items() if any(fnmatch.fnmatch(f, p) for p in pats)]
    return sum(sizes) if sizes else None


def _url_size(url: str) -> Optional[int]:
    """Content-Length of ``url`` from a HEAD request (None when unknown)."""
    import urllib.request

    req = urllib.request.Request(url, method="HEAD", headers={"User-Agent": "ssgwarp"})
    with urllib.request.urlopen(req, timeout=_timeout()) as r:
        n = r.headers.get("Content-Length")
    return int(n) if n else None


def _hf_download(spec: WeightSpec, patterns: list[str], force: bool) -> Path:
    """``snapshot_download`` of ``patterns`` into :func:`hub_cache`; returns the snapshot folder."""
    return Path(_hf().snapshot_download(repo_id=spec.repo, allow_patterns=patterns, cache_dir=str(hub_cache()),
                                        etag_timeout=_timeout(), force_download=force))


@contextlib.contextmanager
def _socket_timeout(seconds: float) -> Iterator[None]:
    old = socket.getdefaulttimeout()
    socket.setdefaulttimeout(seconds)
    try:
        yield
    finally:
        socket.setdefaulttimeout(old)


def _url_download(spec: WeightSpec, dst: Path, progress: bool) -> None:
    """``torch.hub.download_url_to_file`` (temporary file, SHA-256 prefix checked, then moved to ``dst``)."""
    import torch.hub

    dst.parent.mkdir(parents=True, exist_ok=True)
    with _socket_timeout(_timeout() * 3):    # urllib waits forever by default on a stalled connection
        torch.hub.download_url_to_file(spec.url, str(dst), hash_prefix=spec.sha256, progress=progress)


def _network_error(e: BaseException) -> bool:
    """Whether ``e`` means "no network" (then later downloads in this process are not tried)."""
    names = " ".join(c.__name__ for c in type(e).__mro__)
    if any(w in names for w in ("Connect", "Timeout", "LocalEntryNotFound", "OfflineMode", "NetworkError")):
        return True
    return isinstance(e, OSError) and not isinstance(e, (PermissionError, FileNotFoundError, IsADirectoryError))


def fetch(key: str, *, force: bool = False, progress: bool = True, say=None) -> Path:
    """Download weights ``key`` into the ecosystem's cache and return their path.

    Says what, from where, how large and under which licence first (``say``:
    a one-argument callable, default: print to stderr). ``force`` fetches again
    even when cached. Raises :class:`DownloadFailed` (one line) when downloads
    are off or the download fails; a failure for lack of network turns
    downloads off for the rest of the process (no repeated waits).
    """
    global _NETWORK_DOWN
    spec = _spec(key)
    say = say or (lambda m: print(m, file=sys.stderr, flush=True))
    if not (spec.repo or spec.url):
        raise DownloadFailed(f"{key} has no public download: {_alternatives(spec)}")
    off = offline_reason()
    if off:
        raise DownloadFailed(message(key, reason=f"downloads are off: {off}"))
    if spec.repo and _hf() is None:
        raise DownloadFailed(message(key, reason="huggingface_hub is not installed: pip install 'ssgwarp[diffusion]'"))
    src = f"huggingface.co/{spec.repo}" if spec.repo else spec.url
    down = probe(src)
    if down:
        raise DownloadFailed(message(key, reason=f"downloads are off: {down}"))
    listing = None
    try:
        if spec.repo:
            listing = _hub_files(spec)
            size = _download_size(spec, listing)
        else:
            size = _url_size(spec.url)
        known = "" if size else "~"
    except Exception:     # metadata unreachable: say the spec's size; the download itself decides
        size, known = spec.size, "~"
    say(f"ssgwarp: downloading {key} ({spec.title}) from {src}: {known}{_human(size or spec.size)} "
        f"into {_where_to(spec)}; licence {spec.licence}")
    try:
        if spec.repo:
            _hf_download(spec, _patterns(spec, listing), force)
        else:
            _url_download(spec, torch_checkpoints() / spec.filename, progress)
    except KeyboardInterrupt:
        raise
    except Exception as e:
        detail = " ".join(str(e).split())[:300] or type(e).__name__
        if _network_error(e):
            _NETWORK_DOWN = f"downloading {key} failed: {detail}"
            if not _VERBOSE:
                detail = " ".join(detail.split()[:12]) + (" ..." if len(detail.split()) > 12 else "")
        if "hash" in detail.lower():
            detail += " — the download was discarded, nothing was written"
        raise DownloadFailed(message(key, reason=f"download failed: {detail}")) from None
    got = _cache_path(spec)
    if got is None:
        raise DownloadFailed(message(key, reason=f"the download from {src} did not produce {spec.expected}"))
    return got[0]


def require(key: str, explicit: Optional[str | os.PathLike] = None,
            config: Optional[Mapping[str, str]] = None, *, download: Optional[bool] = None,
            progress: bool = True) -> Path:
    """The path of weights ``key``: found locally (:func:`find`), else downloaded (:func:`fetch`).

    ``download``: None (default) downloads unless downloads are off
    (:func:`offline_reason`); False never downloads. Raises
    :class:`WeightsNotFound` (:class:`DownloadFailed` when a download was
    tried) with a one-line message naming ``ssgwarp weights --download KEY``
    and the explicit-path alternatives. An explicit path that does not exist is
    an error, never a download.
    """
    p = find(key, explicit, config)
    if p is not None:
        return p
    if explicit:
        raise WeightsNotFound(message(key, explicit))
    spec = _spec(key)
    off = offline_reason() if download is not False else "downloads not allowed here"
    if off or not (spec.repo or spec.url):
        raise WeightsNotFound(message(key, reason=f"downloads are off: {off}" if off else None))
    return fetch(key, progress=progress)


def obtain(key: str, explicit: Optional[str | os.PathLike] = None, config: Optional[Mapping[str, str]] = None,
           *, instead: str = "", download: Optional[bool] = None) -> Optional[Path]:
    """:func:`require`, or None where a stage can run without the weights.

    A missing model is reported in one short line on stderr, once per model and
    command (:func:`notice`; ``instead`` says what runs in their place).
    """
    try:
        return require(key, explicit, config, download=download)
    except WeightsNotFound as e:
        if explicit and not isinstance(e, DownloadFailed):
            raise
        notice(key, str(e), instead)
        return None


# -- the table -----------------------------------------------------------------------------------------
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


def _expand(names: Iterable[str]) -> list[str]:
    out: list[str] = []
    for n in names:
        for k in GROUPS.get(n, (n,)):
            _spec(k)
            if k not in out:
                out.append(k)
    return out


_GROUPS_HELP = ", ".join(g + " = " + " + ".join(v) for g, v in GROUPS.items())


# -- `ssgwarp weights` ----------------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--download", nargs="*", metavar="NAME", default=None,
                   help=f"fetch these models into the Hugging Face / torch hub caches (all when no NAME): "
                        f"{', '.join(SPECS)}, or a group: {_GROUPS_HELP}")
    p.add_argument("--force", action="store_true", help="with --download: fetch again even when cached")
    p.add_argument("--verify", action="store_true",
                   help="check the found files against their published hashes (reads every file)")


def run(args) -> int:
    with verbose():            # this command is where the long forms belong
        return _run(args)


def _run(args) -> int:
    cfg = getattr(args, "weights", None)
    cfg = cfg if isinstance(cfg, Mapping) else None
    if args.download is not None:
        keys = _expand(args.download) if args.download else list(SPECS)
        off = offline_reason()
        if off:
            raise SsgwarpError(f"--download: downloads are off ({off}); run it on a machine with network "
                               f"without --offline / SSGWARP_OFFLINE / HF_HUB_OFFLINE")
        failed = []
        for key in keys:
            if not args.force and locate(key, config=cfg) is not None:
                print(f"ssgwarp weights: {key} already here ({find(key, config=cfg)})")
                continue
            try:
                fetch(key, force=args.force)
            except DownloadFailed as e:
                failed.append(key)
                print(f"ssgwarp weights: {e}", file=sys.stderr)
        print(table(config=cfg, check=args.verify))
        if failed:
            raise SsgwarpError(f"could not download {', '.join(failed)} (see the messages above)")
        return 0
    print(table(config=cfg, check=args.verify))
    return 0
