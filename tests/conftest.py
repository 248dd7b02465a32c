from pathlib import Path

import pytest
import torch

torch.set_num_threads(1)  # the tests' tensors are tiny: threads cost more than they give

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def fail_on_call(monkeypatch):
    """``fail_on_call(owner, name, n, how)`` replaces ``owner.name`` so that its ``n``-th call raises
    ``KeyboardInterrupt`` before running (``how="interrupt"``, a Ctrl-C) or returns its result times
    NaN (``how="nan"``, a diverging loss); returns the original, to put back with ``monkeypatch``."""

    def install(owner, name: str, n: int, how: str):
        if how not in ("interrupt", "nan"):
            raise ValueError(f"fail_on_call: how must be 'interrupt' or 'nan', got {how!r}")
        orig, calls = getattr(owner, name), {"n": 0}

        def wrapper(*args, **kwargs):
            calls["n"] += 1
            if how == "interrupt" and calls["n"] == n:
                raise KeyboardInterrupt
            value = orig(*args, **kwargs)
            return value * float("nan") if how == "nan" and calls["n"] == n else value

        monkeypatch.setattr(owner, name, wrapper)
        return orig

    return install


@pytest.fixture(scope="session", autouse=True)
def _release_vtk_objects():
    """Free pyvista/VTK objects before interpreter shutdown (their late __del__ prints noise)."""
    yield
    import gc
    import sys

    pv = sys.modules.get("pyvista")
    if pv is not None:
        pv.close_all()
        getattr(pv.plotting.plotter, "_ALL_PLOTTERS", {}).clear()
    gc.collect()
