"""Atomic file writes and image I/O through OpenImageIO.

Every file ssgwarp writes goes through :func:`atomic_path` (write to a temporary
name in the same folder, then ``os.replace``), so an interrupted run never
leaves a half-written file behind.

Images are float32 numpy arrays ``[H, W, C]`` in [0, 1] (8-bit formats) or raw
values (EXR).
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it into place.

    On any exception (KeyboardInterrupt included) the temporary file is removed
    and ``path`` is left as it was.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix + ".tmp", dir=path.parent)
    except OSError as e:            # (named as the user wrote it, not as the hidden temporary name)
        raise InputError(f"{path}: cannot write there ({e.strerror or e})") from None
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if e.filename is not None and str(tmp) in (str(e.filename), str(e.filename2)):
            raise OSError(e.errno, f"{path}: cannot write ({e.strerror})") from None
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not valid JSON (not UTF-8 text at byte {e.start})") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (nested too deeply)") from None


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


MAX_IMAGE_VALUES = 1 << 30   # width x height x channels above this is refused before decoding (4 GiB as float32)


def read_image_native(path: str | os.PathLike, fmt: str = "float", what: str = "image") -> np.ndarray:
    """Decode an image file with OpenImageIO as ``[H, W, C]`` in ``fmt`` ("float" or the file's own
    ``"native"`` type).

    A missing, unreadable, truncated or corrupt file (the decoder's own errors and warnings, e.g.
    libjpeg's "Premature end of JPEG file", which otherwise decodes the missing part as grey) and a
    header that claims more than :data:`MAX_IMAGE_VALUES` values raise :class:`InputError` naming
    ``path``; nothing is decoded into a partly valid image.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    from .native_stderr import captured, summary

    data, err, spec = None, "", None
    with captured() as said:        # libpng & co. print on stderr: their words go into our one line
        inp = oiio.ImageInput.open(str(path))
        if inp is not None:
            try:
                spec = inp.spec()
                n = int(spec.width) * int(spec.height) * int(spec.nchannels)
                if spec.width <= 0 or spec.height <= 0 or spec.nchannels <= 0:
                    err = f"its header says {spec.width}x{spec.height} with {spec.nchannels} channels"
                elif n > MAX_IMAGE_VALUES:
                    err = (f"its header says {spec.width}x{spec.height} with {spec.nchannels} channels, "
                           f"more than ssgwarp reads ({MAX_IMAGE_VALUES} values)")
                else:
                    data = inp.read_image(0, 0, 0, spec.nchannels, spec.format if fmt == "native" else fmt)
                    err = inp.geterror() or ""
            finally:
                inp.close()
    if inp is None:
        detail = " ".join((oiio.geterror() or summary(said) or "unknown format").split())
        raise InputError(f"{path}: cannot read {what} ({detail})")
    oiio.geterror()                 # clear OIIO's global error, so none is left pending at exit
    if data is None and err.startswith("its header"):
        raise InputError(f"{path}: not a usable {what}: {err}")
    if err or data is None or not isinstance(data, np.ndarray):
        detail = "; ".join(t for t in (" ".join(err.split()), summary(said)) if t)
        raise InputError(f"{path}: cannot decode {what} ({detail + '; ' if detail else ''}truncated or corrupt?)")
    return np.asarray(data).reshape(spec.height, spec.width, spec.nchannels)


def read_image(path: str | os.PathLike, channels: int | None = None) -> np.ndarray:
    """Read an image with OpenImageIO as float32 ``[H, W, C]``.

    8-bit and 16-bit files are scaled to [0, 1]; float files (EXR) keep their
    values. ``channels`` keeps the first ``channels`` channels (a grey image is
    repeated to 3 when 3 are asked for). A missing, truncated or corrupt file raises
    :class:`InputError` naming it (:func:`read_image_native`).
    """
    path = Path(path)
    img = np.asarray(read_image_native(path, "float"), dtype=np.float32)
    if channels is not None:
        if img.shape[2] == 1 and channels >= 3:
            img = np.repeat(img, 3, axis=2)
            if channels == 4:
                img = np.concatenate([img, np.ones_like(img[..., :1])], axis=2)
        elif img.shape[2] < channels:
            if channels == 4 and img.shape[2] == 3:
                img = np.concatenate([img, np.ones_like(img[..., :1])], axis=2)
            else:
                raise InputError(f"{path}: has {img.shape[2]} channels, {channels} needed")
        img = img[..., :channels]
    return np.ascontiguousarray(img)


PNG_LEVEL = 1   # zlib level of written PNGs: about 4x faster than libpng's default (6) for files ~7 % larger


def write_image(path: str | os.PathLike, img: Any) -> Path:
    """Write ``img`` (``[H, W]`` or ``[H, W, C]``, numpy or torch) atomically.

    PNG/JPEG are written as 8-bit after clipping to [0, 1] (PNG at zlib level :data:`PNG_LEVEL`); EXR as float32.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if hasattr(img, "detach"):
        img = img.detach().cpu().numpy()
    img = np.asarray(img, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3:
        raise ValueError(f"write_image: expected [H, W, C], got shape {img.shape}")
    h, w, c = img.shape
    ext = path.suffix.lower()
    if ext in (".exr", ".hdr"):
        fmt, data = "float", img
    else:
        fmt, data = "uint8", (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        # OIIO picks the format from the file name: give the temp file the real suffix
        out = oiio.ImageOutput.create(ext.lstrip(".") or "png")
        if out is None:
            raise InputError(f"{path}: no image writer for '{ext}' ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        if ext == ".png":
            spec.attribute("png:compressionLevel", PNG_LEVEL)
        if not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot write image ({out.geterror()})")
        out.write_image(np.ascontiguousarray(data))
        out.close()
    return path


def image_bytes(img: Any) -> np.ndarray:
    """``img`` (``[H, W]`` or ``[H, W, C]``, numpy or torch on any device) as a float32 numpy array of its own
    (a copy: the caller may change or free ``img`` right after; a torch tensor is read back here)."""
    if hasattr(img, "detach"):
        img = img.detach().cpu().numpy()
    return np.array(img, dtype=np.float32, copy=True)


class ImageWriter:
    """Writes files on background threads while the caller goes on (renders the next view): PNG encoding
    and the disk are off the caller's path.

    ``image(path, img)`` copies ``img`` to the CPU at once and queues :func:`write_image` (atomic: a file is
    either whole or absent); ``call(fn, *args)`` queues any other writer (e.g. the path video). Used as a
    context manager: leaving the block waits for every queued write and raises the first error of any
    (also a write's error is raised by the next ``image``/``call``, so a failing disk stops the work
    early). When the block ends by an exception (Ctrl-C included), writes not yet started are dropped,
    the running ones finish (each atomic, so nothing half-written is left), and the exception goes on.
    ``workers``: threads (default: 2, or 1 on a single core); at most ``4 * workers`` writes wait in the
    queue (their images held in memory): a further one waits for the oldest to finish. ``paths``: the
    queued files, in the order they were queued; ``cpu``: the CPU seconds the threads spent writing.
    """

    def __init__(self, workers: int | None = None):
        import concurrent.futures as cf

        n = max(1, int(workers if workers is not None else min(2, os.cpu_count() or 1)))
        self._pool = cf.ThreadPoolExecutor(n, thread_name_prefix="ssgwarp-write")
        self._max_pending = 4 * n
        self._futures: list = []   # (the writes not known to have succeeded, oldest first)
        self.paths: list[Path] = []
        self.cpu = 0.0
        self._lock = threading.Lock()

    def image(self, path: str | os.PathLike, img: Any) -> Path:
        """Queue ``img`` to be written to ``path`` (:func:`write_image`); returns ``path``."""
        return self.call(write_image, Path(path), image_bytes(img))

    def call(self, fn, path: str | os.PathLike, *args, **kwargs) -> Path:
        """Queue ``fn(path, *args, **kwargs)`` (a writer of ``path``, atomic itself); returns ``path``."""
        import concurrent.futures as cf

        self._raise_done()
        while len(self._futures) >= self._max_pending:   # (bounded memory: wait for the oldest)
            cf.wait(self._futures[:1])
            self._raise_done()
        self._futures.append(self._pool.submit(self._timed, fn, Path(path), *args, **kwargs))
        self.paths.append(Path(path))
        return Path(path)

    def _timed(self, fn, *args, **kwargs):
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            with self._lock:
                self.cpu += time.thread_time() - t0

    def _raise_done(self) -> None:
        """Forget the writes that succeeded; on the first that failed, stop the others and raise its error."""
        for f in self._futures:
            if f.done() and not f.cancelled() and f.exception() is not None:
                self.close(cancel=True)
        self._futures = [f for f in self._futures if not f.done()]

    def close(self, cancel: bool = False) -> None:
        """Wait for the queued writes (``cancel``: drop those not started) and raise the first error."""
        import concurrent.futures as cf

        if cancel:
            for f in self._futures:
                f.cancel()
        err: BaseException | None = None
        while True:
            try:
                cf.wait(self._futures)
                break
            except KeyboardInterrupt as e:   # a second Ctrl-C: drop what has not started, still wait for the rest
                err = err or e
                for f in self._futures:
                    f.cancel()
        self._pool.shutdown(wait=True)
        if err is not None:
            raise err
        for f in self._futures:
            if not f.cancelled() and f.exception() is not None:
                raise f.exception()

    def __enter__(self) -> "ImageWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        try:
            self.close(cancel=True)
        except BaseException:   # (the block's own exception goes on; a write's error behind it is dropped)
            pass
