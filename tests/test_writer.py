"""ssgwarp.core.fileio.ImageWriter: images encoded and written on background threads (stylize's renders and path
frames), each file whole or absent, every error raised, nothing left behind by Ctrl-C."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from ssgwarp.core.fileio import ImageWriter, read_image, write_image
from ssgwarp.errors import InputError


def _img(i: int) -> torch.Tensor:
    return torch.rand(9, 11, 3, generator=torch.Generator().manual_seed(i))


def test_every_image_lands_whole_with_its_own_pixels_in_queue_order(tmp_path):
    buf = _img(0)
    with ImageWriter(workers=2) as w:
        for i in range(12):
            buf.copy_(_img(i))
            w.image(tmp_path / "sub" / f"f{i:02d}.png", buf)   # (the buffer is overwritten right after: copied)
    assert w.paths == [tmp_path / "sub" / f"f{i:02d}.png" for i in range(12)] and w.cpu > 0
    for i in range(12):
        got = read_image(tmp_path / "sub" / f"f{i:02d}.png")
        assert np.abs(got - _img(i).numpy()).max() <= 0.5 / 255 + 1e-6, i
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == [f"f{i:02d}.png" for i in range(12)]  # no temp files


def test_a_failed_write_is_raised_at_the_end_and_by_the_next_queued_write(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="cannot write there"):
        with ImageWriter() as w:
            w.image(tmp_path / "file" / "a.png", _img(0))     # its folder is a file
    failed = threading.Event()

    def fails(path):
        failed.set()
        raise OSError(f"{path}: disk full")

    w = ImageWriter(workers=1)
    w.call(fails, tmp_path / "b.png")
    failed.wait(5)
    w._futures[0].exception(timeout=5)   # (finished)
    with pytest.raises(OSError, match="disk full"):
        w.image(tmp_path / "c.png", _img(1))
    assert not (tmp_path / "c.png").exists()


def test_ctrl_c_lets_the_running_write_finish_and_drops_the_queued_ones(tmp_path):
    release, started = threading.Event(), threading.Event()

    def slow(path, img):
        started.set()
        release.wait(5)
        write_image(path, img)

    with pytest.raises(KeyboardInterrupt):
        with ImageWriter(workers=1) as w:
            w.call(slow, tmp_path / "running.png", _img(0).numpy())
            for i in range(3):
                w.image(tmp_path / f"queued{i}.png", _img(i))
            started.wait(5)
            threading.Timer(0.2, release.set).start()   # (the running write ends after the interrupt)
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["running.png"]        # whole; the rest dropped, no temp files
    assert np.abs(read_image(tmp_path / "running.png") - _img(0).numpy()).max() <= 0.5 / 255 + 1e-6
