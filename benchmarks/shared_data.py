"""Where the benchmark scripts find the shared captures (run as ``python benchmarks/<name>.py``, which
puts this folder on ``sys.path``)."""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# beside the repository (the development machines), the GPU machine's copy, a checkout inside the
# repository, the shared copy of a worktree
CANDIDATES = (ROOT.parent / "shared" / "data", Path("/root/data"), ROOT / "shared" / "data", Path("/work/shared/data"))


def data_root() -> Path:
    """The first candidate folder that exists (the first one when none does, for the error message)."""
    return next((p for p in CANDIDATES if p.is_dir()), CANDIDATES[0])
