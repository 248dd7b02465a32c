"""PLY in the INRIA 3DGS layout: bit-exact round trips, the field order viewers expect,
channel-major f_rest, identity fields, and clear errors for bad files."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from ssgwarp.errors import InputError
from ssgwarp.formats.ply import field_names, read_ply, write_ply
from ssgwarp.raster.scene import GaussianScene


def _scene(n=50, degree=2, identities=0, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    return GaussianScene(
        torch.randn(n, 3, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
        torch.randn(n, generator=g), torch.randn(n, 3, generator=g),
        torch.randn(n, k, 3, generator=g) if k else None,
        torch.randn(n, identities, generator=g) if identities else None, degree)


def _same(a: GaussianScene, b: GaussianScene):
    assert a.sh_degree == b.sh_degree
    ta, tb = a.tensors(), b.tensors()
    assert set(ta) == set(tb)
    for k in ta:
        assert ta[k].dtype == tb[k].dtype == torch.float32
        # bit-exact, NaN-free by construction
        assert torch.equal(ta[k].view(torch.int32), tb[k].view(torch.int32)), k


@pytest.mark.parametrize("degree,ident", [(0, 0), (1, 0), (2, 16), (3, 0), (3, 8)])
def test_round_trip_bit_exact(tmp_path, degree, ident):
    s = _scene(degree=degree, identities=ident)
    write_ply(tmp_path / "s.ply", s)
    r = read_ply(tmp_path / "s.ply")
    _same(s, r)
    if degree == 0:
        assert r.sh_rest is None  # a degree-0 scene holds no higher bands
    if not ident:
        assert r.identities is None
    assert not [p for p in tmp_path.iterdir() if p.name != "s.ply"]  # no temporary files left


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(width=32, allow_nan=False, allow_infinity=False), min_size=14, max_size=14))
def test_round_trip_extreme_values(tmp_path_factory, vals):
    """Subnormals, -0.0, huge and tiny magnitudes survive unchanged."""
    v = torch.tensor(vals, dtype=torch.float32)
    q = v[6:10].clone()
    if bool((q == 0).all()):
        q[0] = 1.0
    s = GaussianScene(v[0:3][None], v[3:6][None], q[None], v[10:11], v[11:14][None])
    p = tmp_path_factory.mktemp("h") / "s.ply"
    write_ply(p, s)
    _same(s, read_ply(p))


def test_inria_layout_and_channel_major_f_rest(tmp_path):
    from plyfile import PlyData

    s = _scene(n=4, degree=1, identities=3)
    k = 3
    rest = torch.zeros(4, k, 3)
    for kk in range(k):
        for c in range(3):
            rest[:, kk, c] = 100 * c + kk
    s = s.replace(sh_rest=rest)
    write_ply(tmp_path / "s.ply", s)
    ply = PlyData.read(str(tmp_path / "s.ply"))
    names = [p.name for p in ply["vertex"].properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(9)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
                        "obj_dc_0", "obj_dc_1", "obj_dc_2"])
    assert names == field_names(1, 3)
    v = ply["vertex"].data
    for kk in range(k):
        for c in range(3):  # INRIA flattens [N, 3, K]: f_rest_{c*K + k}
            assert np.all(v[f"f_rest_{c * k + kk}"] == 100 * c + kk)
    assert np.all(v["opacity"] == s.logit_opacities.numpy())  # logits, not probabilities
    assert np.all(v["scale_1"] == s.log_scales[:, 1].numpy())  # log scales
    assert np.all(v["rot_0"] == s.quats[:, 0].numpy())  # w first
    assert ply.elements[0].properties[0].val_dtype in ("f4", "float32", "float")


def _write_fields(path, fields: dict[str, np.ndarray]):
    from plyfile import PlyData, PlyElement

    n = len(next(iter(fields.values())))
    arr = np.zeros(n, dtype=[(k, v.dtype) for k, v in fields.items()])
    for k, v in fields.items():
        arr[k] = v
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(path))


def _fields(n=3, rest=0, extra=()):
    f = {nm: np.ones(n, np.float32) for nm in field_names(0)}
    for i in range(rest):
        f[f"f_rest_{i}"] = np.zeros(n, np.float32)
    for nm in ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"):
        f[nm] = np.ones(n, np.float32)
    for nm in extra:
        f[nm] = np.zeros(n, np.float32)
    return f


def test_bad_files(tmp_path):
    s = _scene(n=20, degree=1)
    good = tmp_path / "good.ply"
    write_ply(good, s)
    data = good.read_bytes()
    cases = {
        "truncated": data[: len(data) - 37],
        "header_only": data[: data.index(b"end_header") + 11],
        "not_ply": b"hello world\n",
        "empty": b"",
    }
    for name, content in cases.items():
        p = tmp_path / f"{name}.ply"
        p.write_bytes(content)
        with pytest.raises(InputError, match="corrupt or truncated|no Gaussians"):
            read_ply(p)
    with pytest.raises(InputError, match="not found"):
        read_ply(tmp_path / "missing.ply")

    _write_fields(tmp_path / "extra.ply", _fields(extra=("red",)))
    with pytest.raises(InputError, match="unexpected PLY field.*red"):
        read_ply(tmp_path / "extra.ply")
    f = _fields()
    del f["rot_3"]
    _write_fields(tmp_path / "missing_field.ply", f)
    with pytest.raises(InputError, match="missing field.*rot_3"):
        read_ply(tmp_path / "missing_field.ply")
    _write_fields(tmp_path / "rest5.ply", _fields(rest=5))
    with pytest.raises(InputError, match="5 f_rest_\\* fields match no SH degree"):
        read_ply(tmp_path / "rest5.ply")
    f = _fields()
    f["scale_2"][1] = np.nan
    _write_fields(tmp_path / "nan.ply", f)
    with pytest.raises(InputError, match="1 Gaussian\\(s\\) have NaN/inf scale"):
        read_ply(tmp_path / "nan.ply")
    f = _fields()
    f["x"][0] = np.inf
    _write_fields(tmp_path / "inf.ply", f)
    with pytest.raises(InputError, match="NaN/inf position"):
        read_ply(tmp_path / "inf.ply")
    f = _fields()
    f["opacity"] = np.ones(3, np.int32)
    _write_fields(tmp_path / "int.ply", f)
    with pytest.raises(InputError, match="type"):
        read_ply(tmp_path / "int.ply")
    # files without normals (some exporters drop them) still load
    f = _fields()
    for nm in ("nx", "ny", "nz"):
        del f[nm]
    _write_fields(tmp_path / "nonormals.ply", f)
    assert len(read_ply(tmp_path / "nonormals.ply")) == 3


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    import plyfile

    p = tmp_path / "s.ply"
    write_ply(p, _scene(n=5, degree=0))
    before = p.read_bytes()

    def boom(self, stream):
        raise KeyboardInterrupt

    monkeypatch.setattr(plyfile.PlyData, "write", boom)
    with pytest.raises(KeyboardInterrupt):
        write_ply(p, _scene(n=7, degree=1))
    assert p.read_bytes() == before
    assert [q.name for q in tmp_path.iterdir()] == ["s.ply"]
