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
