import os
import sys
from pathlib import Path

# The tests import the installed package (``pip install -e .``: ssgwarp, with kernels/ and viewer/ as
# ssgwarp.kernels and ssgwarp.viewer), never the checkout's folders as top-level packages: ``python -m pytest``
# (the README's command) puts the working directory on sys.path, and pytest-xdist's workers start from the
# controller's sys.path, so with the checkout's root there its kernels/ would hide the registry package
# ``kernels`` that transformers imports. This runs before any test module is imported, in the controller and in
# every worker (tests/test_packaging.py checks the outcome).
ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or os.getcwd()).resolve() != ROOT]

import importlib.util  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

_ROOT_REAL = os.path.realpath(ROOT)


@pytest.fixture(autouse=True)
def _checkout_root_stays_off_sys_path():
    """A test (or a script it loads: benchmarks/, docs/) that puts the checkout's root back on sys.path fails."""
    yield
    back = [p for p in sys.path if os.path.realpath(p or os.curdir) == _ROOT_REAL]
    if back:   # (taken off again, so that only the test that put it there fails)
        sys.path[:] = [p for p in sys.path if p not in back]
    assert not back, f"the checkout's root is on sys.path again ({back}): import the installed package instead"


if importlib.util.find_spec("ssgwarp") is None:
    pytest.exit(f"ssgwarp is not installed: run `python -m pip install -e '.[dev]'` in {ROOT} first", returncode=4)

torch.set_num_threads(1)  # the tests' tensors are tiny: threads cost more than they give

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

CUDA = torch.cuda.is_available()
# marks of a test (or a parameter value) that needs CUDA: the GPU machine runs every such test with
# ``python -m pytest -m cuda tests`` (docs/testing.md); elsewhere they skip
CUDA_ONLY = [pytest.mark.cuda, pytest.mark.skipif(not CUDA, reason="needs a CUDA device")]


def assert_close_elementwise(actual, expected, rtol: float, atol: float, name: str = "tensor",
                             ulps: float = 0.0, truth=None) -> None:
    """Every entry within ``atol + rtol * |expected| + ulps * eps * max|expected|``.

    Per entry, not relative to the tensor's largest entry, so small entries are checked too; ``ulps``
    (units of roundoff of ``expected``'s dtype, times its largest entry) admits the rounding noise of
    sums whose terms cancel: a gradient entry near 0 that sums terms as large as the largest entry
    is only known to that precision. The message names the worst entry, its values and the bound.

    With ``truth`` (a more precise computation of the same quantity, e.g. float64), ``expected`` is
    itself an approximation, and an entry passes when ``actual`` is no farther from the truth than
    ``expected`` is, plus the bound: ``|actual - truth| <= |expected - truth| + bound``. That admits
    every entry the plain check admits (triangle inequality) and, beyond it, only disagreements where
    ``expected`` carries the larger error.
    """
    actual, expected = torch.as_tensor(actual), torch.as_tensor(expected)
    assert actual.shape == expected.shape, f"{name}: shape {tuple(actual.shape)} != {tuple(expected.shape)}"
    eps = torch.finfo(expected.dtype).eps if expected.dtype.is_floating_point else 0.0
    a, b = actual.detach().double().cpu(), expected.detach().double().cpu()
    assert torch.isfinite(a).all(), f"{name}: non-finite values"
    if a.numel() == 0:
        return
    floor = atol + ulps * eps * b.abs().max().item()
    bound = floor + rtol * b.abs()
    if truth is None:
        excess = (a - b).abs() - bound
    else:
        t = torch.as_tensor(truth).detach().double().cpu()
        assert t.shape == a.shape, f"{name}: truth's shape {tuple(t.shape)} != {tuple(a.shape)}"
        excess = (a - t).abs() - (b - t).abs() - bound
    worst = int(excess.reshape(-1).argmax())
    if excess.reshape(-1)[worst] > 0:
        idx = tuple(int(i) for i in torch.unravel_index(torch.tensor(worst), a.shape))
        n_bad = int((excess > 0).sum())
        raise AssertionError(f"{name}: {n_bad} of {a.numel()} entries off; worst at {idx}: {a[idx].item():.6e} vs "
                             f"{b[idx].item():.6e} (|diff| {abs(a[idx] - b[idx]).item():.3e} > bound "
                             f"{bound[idx].item():.3e} = {floor:.3e} + {rtol:g} * |expected|)"
                             + ("" if truth is None else f"; truth {t[idx].item():.6e}: |actual - truth| "
                                f"{abs(a[idx] - t[idx]).item():.3e} > |expected - truth| {abs(b[idx] - t[idx]).item():.3e}"
                                " + bound"))


def pytest_collection_modifyitems(config, items):
    """Files holding ``slow`` tests first, the most slow tests first (the order within a file kept).

    With ``-n 2`` (the README's command; ``--dist loadfile`` from pyproject.toml) each file goes to one
    worker as a whole, in this order: the longest files start first, so that neither worker is left
    with one of them at the end while the other is idle."""
    slow = {}
    for item in items:
        slow.setdefault(item.path, 0)
        slow[item.path] += item.get_closest_marker("slow") is not None
    rank = {path: i for i, path in enumerate(sorted(slow, key=lambda p: -slow[p]))}   # (sorted is stable)
    items.sort(key=lambda item: rank[item.path])


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


# ----------------------------------------------------------------------------- no weights, no network
WEIGHT_ENV = ("SSGWARP_WEIGHTS", "SSGWARP_SD15", "SSGWARP_CONTROLNET_DEPTH", "SSGWARP_IP_ADAPTER",
              "SSGWARP_IMAGE_ENCODER", "SSGWARP_VGG16", "SSGWARP_RAFT", "SSGWARP_LPIPS", "SSGWARP_SAM",
              "HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE")


class NetworkUsed(BaseException):
    """Raised by any test that opens an internet connection (BaseException: no ``except Exception`` hides it)."""


@pytest.fixture(scope="session")
def _empty_caches(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("empty-weight-caches")


@pytest.fixture(autouse=True)
def _no_weights_no_network(monkeypatch, _empty_caches):
    """Every test sees no pretrained weights (empty HF_HOME / TORCH_HOME, no SSGWARP_* paths), downloads off,
    and fails loudly on a DNS lookup or connection to anything but this machine."""
    import socket

    from ssgwarp.services import weights

    monkeypatch.setattr(weights, "_NETWORK_DOWN", None)    # per-process download state starts afresh
    monkeypatch.setattr(weights, "_OFFLINE_FLAG", None)
    monkeypatch.setattr(weights, "_NETWORK_OK", None)       # the network probe's kept answer
    monkeypatch.setattr(weights, "_SAID", set())            # missing models reported once per command
    for var in WEIGHT_ENV:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HF_HOME", str(_empty_caches / "huggingface"))
    monkeypatch.setenv("TORCH_HOME", str(_empty_caches / "torch"))
    for var in ("SSGWARP_OFFLINE", "HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"):
        monkeypatch.setenv(var, "1")
    local = ("localhost", "127.0.0.1", "::1", "", None)
    real_getaddrinfo, real_connect = socket.getaddrinfo, socket.socket.connect

    def getaddrinfo(host, *a, **kw):
        if host not in local:
            raise NetworkUsed(f"a test looked up {host!r}: tests must never touch the network")
        return real_getaddrinfo(host, *a, **kw)

    def connect(self, address):
        if self.family in (socket.AF_INET, socket.AF_INET6) and address[0] not in local:
            raise NetworkUsed(f"a test connected to {address!r}: tests must never touch the network")
        return real_connect(self, address)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    monkeypatch.setattr(socket.socket, "connect", connect)
