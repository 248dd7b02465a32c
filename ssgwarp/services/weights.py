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
naming the file and how to fetch it again. ``ssgwarp weights`` prints the table and
``ssgwarp weights --download [NAMES]`` fetches (:func:`fetch`): that command and its table live in
:mod:`ssgwarp.services.weights_command`.
"""
from __future__ import annotations

import contextlib
import fnmatch
import importlib
import importlib.util
import os
import socket
import sys
from pathlib import Path
from typing import Iterator, Mapping, Optional

from ..errors import InputError, WeightsNotFound
from .weight_specs import WeightSpec, _spec

__all__ = ["DownloadFailed", "find", "locate", "require", "obtain", "fetch", "message", "notice", "load_error",
           "offline_reason", "offline", "verbose", "probe", "hub_cache", "torch_checkpoints",
           "check_kernels_package"]


class DownloadFailed(WeightsNotFound):
    """A model was missing and downloading it failed (no network, refused, wrong hash)."""


_TRUE = ("1", "true", "yes", "on")
_OFFLINE_FLAG: Optional[str] = None          # set by --offline (offline())
_NETWORK_DOWN: Optional[str] = None          # reason, once a download found no network in this process
_NETWORK_OK: Optional[bool] = None           # True once the probe reached the network (kept for the process)
_VERBOSE: bool = False                       # --debug: messages in their long form
_SAID: set = set()                           # models whose absence this command has reported (notice())


# -- importing the libraries that own the weights ------------------------------------------------
def check_kernels_package() -> None:
    """Refuse, in one line, to go on where ``import kernels`` would load this project's ``kernels/`` folder.

    transformers 5 requires the registry package ``kernels`` (and diffusers imports it where it is installed).
    With a source checkout's root on ``sys.path`` (``python -m ssgwarp ...`` or a script run from there) the
    checkout's ``kernels/`` (installed as ``ssgwarp.kernels``) would be found first and those imports fail deep
    inside transformers. Nothing here changes ``sys.path``: the error names the way out. Call before importing
    diffusers or transformers."""
    found = sys.modules.get("kernels")
    origin = getattr(found, "__file__", None) if found is not None else None
    if found is None:
        spec = importlib.util.find_spec("kernels")
        origin = None if spec is None else spec.origin
    if origin is None:
        return
    ours = Path(importlib.util.find_spec("ssgwarp.kernels").origin).resolve().parent
    if Path(origin).resolve().parent == ours:
        raise InputError(f"the source checkout's folder {ours} hides the `kernels` package that transformers "
                         f"imports (the checkout's root {ours.parent} is on sys.path): run the installed `ssgwarp` "
                         "command (under torchrun: --no-python ssgwarp ...), or run python from another folder")


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
        cost = f" (~{_human(spec.size)})" if spec.size else ""
        flag = spec.flags.split(" (")[0].split(",")[0]
        path = f"pass {flag} PATH or set {spec.env}" if flag else f"set {spec.env}"
        how = f"`ssgwarp weights --download {key}` fetches it{cost}, or {path}" if spec.repo or spec.url else path
        return f"no local {key} weights{why}: {how}"
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
