"""A small reusable fuzzer for file readers (hypothesis): damage a good file, read it, check the outcome.

Usage in a test module::

    from fuzzing import binary_damage, check_reader, fuzz_settings

    @fuzz_settings(300)
    @given(data=binary_damage(GOOD_BYTES))
    def test_fuzz_my_reader(data, tmp_dir):
        check_reader(my_reader, tmp_dir / "file.bin", data)

The contract :func:`check_reader` enforces, for every damaged input:

- the reader returns, or raises one of the user-facing errors (:class:`ssgwarp.errors.SsgwarpError`,
  e.g. ``InputError``); any other exception (IndexError, OverflowError, LinAlgError, ...) fails the case;
- it finishes within ``timeout`` seconds (a hang fails the case);
- its peak Python/numpy allocation (tracemalloc) stays under ``alloc_factor`` x the file's size plus
  ``alloc_slack`` bytes: a count field that claims 2^60 records must be refused, not allocated.

The strategies damage a valid file the ways a disk, a download or another tool does: cut it short (anywhere),
flip bits, overwrite a field with a count-like integer (0, 1, -1, huge; "wrongly counted" and "huge-count"
cases), overwrite with NaN / inf bit patterns, or for text, change tokens into ``nan``/``inf``/huge/negative
numbers and drop or repeat lines. A case can combine up to three damages.

Size: seeded (``derandomize``) and small by default so the suite stays fast; ``SSGWARP_FUZZ_EXAMPLES=N`` runs
N cases per reader instead (the nightly setting of docs/testing.md, e.g. 20000). :data:`COUNTS` records how
many cases each reader survived in this process (``SSGWARP_FUZZ_REPORT=FILE`` appends them to FILE as
``reader cases`` lines at exit).
"""
from __future__ import annotations

import atexit
import collections
import os
import signal
import struct
import tracemalloc
from pathlib import Path
from typing import Any, Callable, Optional

from hypothesis import HealthCheck, settings, strategies as st

from ssgwarp.errors import SsgwarpError

NIGHTLY = int(os.environ.get("SSGWARP_FUZZ_EXAMPLES", "0") or 0)
COUNTS: collections.Counter = collections.Counter()


def fuzz_settings(default_examples: int):
    """hypothesis settings of a fuzz test: ``default_examples`` cases (``SSGWARP_FUZZ_EXAMPLES`` when set),
    derandomized (the same cases every run), no example database, no per-case deadline (the hang check of
    :func:`check_reader` is a hard timeout instead)."""
    return settings(max_examples=NIGHTLY or default_examples, derandomize=True, database=None, deadline=None,
                    suppress_health_check=list(HealthCheck), print_blob=True)


def fuzz_dir(tmp_path_factory):
    """Generator of a scratch folder for the damaged files (in memory, /dev/shm, where there is one: thousands
    of small writes), removed afterwards; use as ``yield from fuzz_dir(tmp_path_factory)`` in a fixture."""
    import shutil
    import tempfile

    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        folder = Path(tempfile.mkdtemp(prefix="ssgwarp-fuzz-", dir=shm))
        try:
            yield folder
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    else:
        yield tmp_path_factory.mktemp("fuzz")


# ----------------------------------------------------------------------------- damage
COUNT_VALUES = (0, 1, 2, 3, 255, 256, 65535, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**48, 2**63 - 1, 2**64 - 1)
FLOAT_SPECIALS = (float("nan"), float("inf"), float("-inf"), 0.0, -0.0, 1e308, -1e308, 1e-308, 3.4e38, -1.0)
TEXT_TOKENS = ("nan", "inf", "-inf", "NaN", "Infinity", "1e400", "-1e400", "0", "-1", "-0", "4294967297",
               "18446744073709551617", "99999999999999999999999", "1.5", "x", "", "\x00", "é", "0x10")


def _truncate(data: bytes, draw) -> bytes:
    return data[: draw(st.integers(0, max(len(data) - 1, 0)))]


def _flip(data: bytes, draw) -> bytes:
    if not data:
        return data
    b = bytearray(data)
    i = draw(st.integers(0, len(b) - 1))
    b[i] ^= 1 << draw(st.integers(0, 7))
    return bytes(b)


def _overwrite(data: bytes, draw, payload: bytes) -> bytes:
    if len(data) < len(payload):
        return data
    i = draw(st.integers(0, len(data) - len(payload)))
    return data[:i] + payload + data[i + len(payload):]


def _count(data: bytes, draw) -> bytes:
    v = draw(st.sampled_from(COUNT_VALUES))
    width = draw(st.sampled_from((4, 8)))
    return _overwrite(data, draw, (v % (1 << (8 * width))).to_bytes(width, "little"))


def _special_float(data: bytes, draw) -> bytes:
    v = draw(st.sampled_from(FLOAT_SPECIALS))
    fmt = draw(st.sampled_from(("<d", "<f")))
    if fmt == "<f" and abs(v) > 3.4e38:
        v = v * float("inf")            # (beyond float32: its infinity)
    return _overwrite(data, draw, struct.pack(fmt, v))


def _splice(data: bytes, draw) -> bytes:
    """A stretch of the file repeated or dropped (records counted wrongly)."""
    if len(data) < 2:
        return data
    i = draw(st.integers(0, len(data) - 1))
    j = draw(st.integers(i, min(len(data), i + 256)))
    return data[:i] + data[i:j] * draw(st.integers(0, 3)) + data[j:]


BINARY_DAMAGES = (_truncate, _flip, _count, _special_float, _splice)


def binary_damage(good: bytes, max_damages: int = 3) -> st.SearchStrategy[bytes]:
    """Strategy: ``good`` with 1 to ``max_damages`` binary damages (truncation, bit flip, count field, NaN/inf,
    spliced stretch)."""

    @st.composite
    def damaged(draw):
        data = good
        for _ in range(draw(st.integers(1, max_damages))):
            data = draw(st.sampled_from(BINARY_DAMAGES))(data, draw)
        return data

    return damaged()


def _lines(text: str, draw) -> str:
    lines = text.split("\n")
    i = draw(st.integers(0, len(lines) - 1))
    return "\n".join(lines[:i] + [lines[i]] * draw(st.integers(0, 3)) + lines[i + 1:])


def _text_truncate(text: str, draw) -> str:
    return text[: draw(st.integers(0, max(len(text) - 1, 0)))]


def text_damage(good: str, max_damages: int = 3, tokens: tuple = TEXT_TOKENS) -> st.SearchStrategy[bytes]:
    """Strategy: the text ``good`` with 1 to ``max_damages`` damages (a token replaced by one of ``tokens``, a
    line dropped or repeated, the text cut short, or, as bytes, a bit flipped); returned as UTF-8 bytes."""

    @st.composite
    def damaged(draw):
        text = good
        flip = False
        for _ in range(draw(st.integers(1, max_damages))):
            kind = draw(st.sampled_from(("token", "token", "lines", "truncate", "flip")))
            if kind == "flip":
                flip = True
            elif kind == "token":
                text = _token(text, draw, tokens)
            else:
                text = (_lines if kind == "lines" else _text_truncate)(text, draw)
        data = text.encode("utf-8")
        return _flip(data, draw) if flip else data

    return damaged()


def _token(text: str, draw, tokens) -> str:
    lines = text.split("\n")
    i = draw(st.integers(0, len(lines) - 1))
    toks = lines[i].split(" ")
    j = draw(st.integers(0, len(toks) - 1))
    toks[j] = draw(st.sampled_from(tokens))
    lines[i] = " ".join(toks)
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the check
class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


def check_reader(read: Callable[[Path], Any], path: Path, data: bytes, *, name: Optional[str] = None,
                 timeout: float = 10.0, alloc_factor: float = 16.0, alloc_slack: int = 4 << 20,
                 ok: tuple = (SsgwarpError,)) -> Any:
    """Write ``data`` to ``path``, call ``read(path)`` and enforce the contract of the module docstring.
    Returns the reader's result, or the user-facing error it raised. Counts the case under ``name``
    (default: the reader's name) in :data:`COUNTS`."""
    path.write_bytes(data)
    name = name or getattr(read, "__name__", "reader")
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout)
    tracemalloc.start()
    try:
        try:
            result = read(path)
        except ok as e:
            result = e
            msg = str(e)
            assert msg and "\n" not in msg.strip(), f"{name}: the error is not one line: {msg!r}"
    except _Hang:
        raise AssertionError(f"{name}: no answer within {timeout} s on {len(data)} bytes (a hang)") from None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    limit = alloc_factor * len(data) + alloc_slack
    assert peak <= limit, f"{name}: allocated {peak} bytes at peak for a {len(data)}-byte file (limit {limit:.0f})"
    COUNTS[name] += 1
    return result


def _report() -> None:
    out = os.environ.get("SSGWARP_FUZZ_REPORT")
    if out and COUNTS:
        with open(out, "a") as f:
            for k, v in sorted(COUNTS.items()):
                f.write(f"{k} {v}\n")


atexit.register(_report)
