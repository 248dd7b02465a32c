"""Progress bars on a terminal; in a log, one line per stage.

:func:`tqdm` is what every stage calls instead of tqdm's own: when stderr is a terminal it is tqdm's bar;
when stderr goes to a file or a pipe (a log, ``nohup``, a batch job) it draws nothing while it runs and
writes one line when a stage's bar ends (``ssgwarp: reconstruct: 1500/1500 steps in 402.1 s``). Bars made
with ``leave=False`` (the sub-steps of a stage: loading images, rendering views) write nothing there. A bar
with ``disable=True`` (``--quiet``) stays silent everywhere.
"""
from __future__ import annotations

import sys
import time
from typing import Any, Iterable, Optional

__all__ = ["tqdm", "on_terminal"]


def on_terminal() -> bool:
    """Whether stderr is an interactive terminal (where a bar can redraw itself)."""
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):
        return False


class LineBar:
    """tqdm's interface as ssgwarp uses it (iterate, ``update``, ``set_description``, ``set_postfix``,
    ``close``, ``with``), silent until it closes; then one line, unless ``leave=False``."""

    def __init__(self, iterable: Optional[Iterable] = None, desc: Optional[str] = None, total: Optional[int] = None,
                 leave: bool = True, unit: str = "it", initial: int = 0, **_: Any):
        self.iterable, self.desc, self.leave, self.unit = iterable, desc, leave, unit
        self.total = total if total is not None or iterable is None or not hasattr(iterable, "__len__") \
            else len(iterable)  # type: ignore[arg-type]
        self.n = self.initial = initial
        self.postfix = ""
        self.start = time.perf_counter()
        self.closed = False

    def __iter__(self):
        try:
            for x in self.iterable or ():
                yield x
                self.n += 1
        finally:
            self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def __enter__(self) -> "LineBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_description(self, desc: Optional[str] = None, refresh: bool = True) -> None:
        self.desc = desc

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kwargs: Any) -> None:
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = s

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if not self.leave or not self.desc:
            return
        done = f"{self.n}/{self.total}" if self.total else f"{self.n}"
        extra = f" ({self.postfix})" if self.postfix else ""
        print(f"ssgwarp: {self.desc}: {done} {self.unit} in {time.perf_counter() - self.start:.1f} s{extra}",
              file=sys.stderr, flush=True)


def tqdm(*args: Any, disable: Optional[bool] = False, **kwargs: Any):
    """tqdm's bar on a terminal, a :class:`LineBar` elsewhere; ``disable=True``: silent (tqdm's no-op)."""
    from tqdm.auto import tqdm as bar

    if disable or on_terminal():
        return bar(*args, disable=bool(disable), **kwargs)
    return LineBar(*args, **kwargs)
