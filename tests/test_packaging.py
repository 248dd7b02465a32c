"""What the package does to the process that imports it: nothing. The tests import the installed package (never
the checkout's top-level folders, which would hide registry packages of the same name), importing ``ssgwarp``
leaves the environment and ``sys.path`` as they were, and the ``ssgwarp`` command sets its OpenMP wait policy
itself, before torch loads."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_import_kernels_gives_the_registry_package_never_the_checkouts_folder():
    """``kernels`` (Hugging Face's package, which transformers 5 imports) is the installed one, or absent; the
    checkout's ``kernels/`` is reachable only as ``ssgwarp.kernels``. CI runs this inside ``python -m pytest -n 2
    tests`` from the checkout's root (the README's command), where both ``python -m`` and the xdist workers start
    with the root on ``sys.path``."""
    assert all(Path(p or os.getcwd()).resolve() != ROOT for p in sys.path), sys.path
    try:
        import kernels
    except ModuleNotFoundError:
        kernels = None
    ours = Path(importlib.util.find_spec("ssgwarp.kernels").origin).resolve().parent
    if kernels is not None:
        assert Path(kernels.__file__).resolve().parent != ours, kernels.__file__
        assert hasattr(kernels, "get_kernel")        # (the registry package's API)
    from ssgwarp.kernels import projection

    assert Path(projection.__file__).resolve().parent == ours


_PROBE = r"""
import os, sys
env, path = dict(os.environ), list(sys.path)
import ssgwarp, ssgwarp.cli
assert dict(os.environ) == env, "import ssgwarp changed the environment"
assert sys.path == path, "import ssgwarp changed sys.path"
assert "torch" not in sys.modules, "import ssgwarp loaded torch"
try:
    ssgwarp.cli.main(["--help"])
except SystemExit:
    pass
print("policy", os.environ.get("OMP_WAIT_POLICY"), "torch" in sys.modules)
env["OMP_WAIT_POLICY"] = "PASSIVE"
assert dict(os.environ) == env and sys.path == path, "the command changed more than its wait policy"
print("lazy", ssgwarp.Cameras.__module__, ssgwarp.InputError.__module__)
"""


def test_importing_ssgwarp_changes_nothing_and_the_command_waits_passively():
    """Importing ``ssgwarp`` sets no environment variable (``OMP_WAIT_POLICY`` was set on import before), adds no
    ``sys.path`` entry and loads no torch; the ``ssgwarp`` command (``cli.main``) sets ``OMP_WAIT_POLICY=PASSIVE``
    before it loads torch (where the user chose no policy: ``setdefault``); the public names load on
    first use."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=120, cwd=Path.home(),
                       env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split("\n")[-3:] == ["policy PASSIVE True", "lazy ssgwarp.core.cameras ssgwarp.errors", ""]
