"""Unit tests of ssgwarp.stylization.matching beside those of tests/test_stylize.py: defaults, messages, options passed on."""
from __future__ import annotations

import pytest
import torch

from ssgwarp.errors import InputError
from ssgwarp.stylization.matching import MatchTargets, downsample_labels, nnfm_loss


def test_downsample_labels_defaults_to_the_majority_vote():
    """A 4x4 map to 1x1: majority gives the id covering most pixels (2, 10 of 16); the nearest pixel to the
    cell centre would give another id (0 at row 2, column 2)."""
    labels = torch.full((1, 4, 4), 2, dtype=torch.long)
    labels[0, 2:, 2:] = 0
    labels[0, 0, 0] = 1
    assert downsample_labels(labels, (1, 1)).tolist() == [[[2]]]
    assert downsample_labels(labels, (1, 1), "majority").tolist() == [[[2]]]
    assert downsample_labels(labels, (1, 1), "nearest").tolist() != [[[2]]]


def test_downsample_labels_names_the_bad_shape():
    with pytest.raises(InputError, match=r"expected \[B,H,W\] labels, got \(4, 4\)"):
        downsample_labels(torch.zeros(4, 4, dtype=torch.long), (2, 2))
    with pytest.raises(InputError, match=r"mode 'mean' \(use majority or nearest\)"):
        downsample_labels(torch.zeros(1, 4, 4, dtype=torch.long), (2, 2), "mean")
    with pytest.raises(InputError, match="^downsample_labels: negative group ids$"):
        downsample_labels(torch.full((1, 4, 4), -1, dtype=torch.long), (2, 2))


def test_nnfm_loss_passes_its_search_precision_on():
    g = torch.Generator().manual_seed(0)
    feats, keys = torch.randn(8, 3, 3, generator=g), torch.randn(2, 8, 4, 4, generator=g)
    with pytest.raises(InputError, match="precision 'fp8'"):
        nnfm_loss(feats, keys, precision="fp8")
    # fp16 search on the CPU: the same neighbours as MatchTargets with that precision, the loss in fp32
    want = MatchTargets(keys, precision="fp16").loss(feats)
    assert torch.equal(nnfm_loss(feats, keys, precision="fp16"), want) and want.dtype == torch.float32


def test_downsample_labels_by_majority_per_cell_with_a_given_group_count():
    """2x2 cells of a 4x4 map, counted by hand; ``num_groups`` wider than the ids present changes nothing,
    and the result is long (group ids index tensors)."""
    labels = torch.tensor([[[0, 0, 1, 1],
                            [0, 2, 1, 3],
                            [2, 2, 3, 3],
                            [2, 0, 3, 1]]])
    want = [[[0, 1], [2, 3]]]
    for k in (None, 4, 7):
        out = downsample_labels(labels, (2, 2), num_groups=k)
        assert out.dtype == torch.long and out.tolist() == want


def test_search_dtype_auto_is_bf16_on_cuda_only():
    from ssgwarp.stylization.matching import search_dtype

    assert search_dtype("auto", "cuda") == search_dtype("auto", "cuda:0") == torch.bfloat16   # no GPU needed
    assert search_dtype("auto", "cpu", torch.float64) == torch.float64
    assert search_dtype("fp16", "cpu") == torch.float16


def test_loss_takes_one_view_with_or_without_its_batch_axis_and_names_bad_shapes():
    g = torch.Generator().manual_seed(1)
    keys, key_labels = torch.randn(2, 8, 4, 4, generator=g), torch.randint(0, 3, (2, 4, 4), generator=g)
    feats, labels = torch.randn(8, 3, 3, generator=g), torch.randint(0, 3, (3, 3), generator=g)
    t = MatchTargets(keys, key_labels)
    want = t.loss(feats, labels)
    assert torch.equal(t.loss(feats[None], labels), want) and torch.equal(t.loss(feats, labels[None]), want)
    with pytest.raises(InputError, match=r": one view at a time$"):
        t.loss(torch.randn(2, 8, 3, 3, generator=g), labels)
    with pytest.raises(InputError, match=r": 5 feature channels, key features have 8$"):
        t.loss(torch.randn(5, 3, 3, generator=g))
    with pytest.raises(InputError, match=r": view labels \(3, 2\) vs features \(3, 3\)$"):
        t.loss(feats, labels[:, :2])


def test_match_targets_names_bad_key_shapes():
    with pytest.raises(InputError, match=r": expected key features \[V,C,h,w\], got \(8, 4, 4\)$"):
        MatchTargets(torch.zeros(8, 4, 4))
    with pytest.raises(InputError, match=r": labels \(2, 4, 3\) do not match features \(2, 4, 4\)$"):
        MatchTargets(torch.zeros(2, 8, 4, 4), torch.zeros(2, 4, 3, dtype=torch.long))
