"""What C libraries print on the process's stderr (file descriptor 2), caught.

libpng (through OpenImageIO) prints ``libpng error: ...`` before our own one-line
error; Warp's native library prints a CUDA-driver warning on every CPU-only machine.
:func:`captured` redirects descriptor 2 into a temporary file for the block and hands
back the lines, so that a caller can fold the useful part into its own message
(:func:`ssgwarp.core.fileio.read_image`) or drop a known-harmless line and pass the
rest on (:func:`replay`).

Only one thread captures at a time: a block entered while another thread captures
runs uncaptured (its lines go to the terminal as before) rather than wait.
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
from typing import Iterable, Iterator

_LOCK = threading.Lock()


@contextlib.contextmanager
def captured() -> Iterator[list[str]]:
    """Catch what is written to descriptor 2 inside the block; the yielded list holds its lines afterwards."""
    lines: list[str] = []
    if not _LOCK.acquire(blocking=False):
        yield lines
        return
    try:
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        try:
            saved = os.dup(2)
        except OSError:              # no descriptor 2 (embedded interpreters): nothing to catch
            yield lines
            return
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield lines
            finally:
                with contextlib.suppress(Exception):
                    sys.stderr.flush()
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                lines.extend(ln for ln in tmp.read().decode("utf-8", "replace").splitlines() if ln.strip())
    finally:
        _LOCK.release()


def replay(lines: Iterable[str], drop: Iterable[str] = ()) -> None:
    """Write ``lines`` to stderr again, except those matching a regular expression of ``drop``."""
    pats = [re.compile(d) for d in drop]
    for ln in lines:
        if not any(p.search(ln) for p in pats):
            print(ln, file=sys.stderr, flush=True)


def summary(lines: Iterable[str], limit: int = 200) -> str:
    """The distinct lines as one line (``a; b``), at most ``limit`` characters."""
    seen: list[str] = []
    for ln in lines:
        ln = " ".join(ln.split())
        if ln and ln not in seen:
            seen.append(ln)
    text = "; ".join(seen)
    return text if len(text) <= limit else text[:limit - 3] + "..."
