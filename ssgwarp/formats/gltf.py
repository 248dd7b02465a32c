"""glTF 2.0 binary (``.glb``) with Khronos's ``KHR_gaussian_splatting`` (release candidate, 2026): one
mesh primitive of mode ``POINTS`` (0) whose attributes are the Gaussians --

* ``POSITION`` (VEC3 float, with min / max as glTF requires);
* ``KHR_gaussian_splatting:ROTATION`` (VEC4 float, unit quaternion in glTF's ``x y z w`` order);
* ``KHR_gaussian_splatting:SCALE`` (VEC3 float, linear: ``exp(log scale)``);
* ``KHR_gaussian_splatting:OPACITY`` (SCALAR float in [0, 1]: ``sigmoid(opacity)``);
* ``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0`` (VEC3 float, ``f_dc``) and, per degree ``l`` the scene
  holds, ``SH_DEGREE_l_COEF_n`` for ``n = 0..2l`` (VEC3 float: the coefficient of order ``m = n - l``
  for r, g, b);
* ``COLOR_0`` (VEC4 unsigned byte, normalised): the base colour and opacity, for viewers without the
  extension (they show a point cloud);

and the extension object ``{"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection":
"perspective", "sortingMethod": "cameraDistance"}``, named in ``extensionsUsed``.

Frames: glTF is y up, +z forward, x left (LUF); our scenes are RDF, so writing and reading rotate by
180 degrees about z: positions ``(-x, -y, z)``, quaternions' ``x`` and ``y`` negated, and each SH
coefficient times its basis function's parity under that flip. Everything is kept at float32 (SH
degree <= 3), so a scene round-trips to float rounding. The reader takes the files this writer makes and
any other of float (or normalised integer) accessors without sparse storage or compression extensions,
whose mesh node has no transform of its own (a node transform is refused, not applied).
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..raster.scene import SH_C0, GaussianScene
from .codec import arrays_scene, logit, scene_arrays, sigmoid, to_u8, write_atomic
from .spz import sh_flip_signs

EXT = "KHR_gaussian_splatting"
RDF_TO_LUF = (-1.0, -1.0, 1.0)
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
# componentType -> (numpy dtype, divisor when normalised)
_TYPES = {5126: ("<f4", None), 5120: ("i1", 127.0), 5121: ("u1", 255.0), 5122: ("<i2", 32767.0),
          5123: ("<u2", 65535.0)}


def _sh_names(degree: int) -> list[str]:
    return [f"{EXT}:SH_DEGREE_{l}_COEF_{n}" for l in range(1, degree + 1) for n in range(2 * l + 1)]


def glb_bytes(scene: GaussianScene) -> bytes:
    """The GLB file of ``scene`` (see the module docs)."""
    a = scene_arrays(scene)
    n, deg = len(scene), scene.sh_degree
    f = np.array(RDF_TO_LUF)
    q = a["quats"]
    attrs = {"POSITION": (a["means"] * f).astype("<f4"),
             f"{EXT}:ROTATION": np.stack([q[:, 1] * f[0], q[:, 2] * f[1], q[:, 3] * f[2], q[:, 0]], 1).astype("<f4"),
             f"{EXT}:SCALE": np.exp(a["log_scales"].astype(np.float64)).astype("<f4"),
             f"{EXT}:OPACITY": sigmoid(a["opacity"]).astype("<f4"),
             f"{EXT}:SH_DEGREE_0_COEF_0": a["sh_dc"].astype("<f4")}
    if deg:
        k = (deg + 1) ** 2 - 1
        rest = a["sh_rest"].astype(np.float64) * sh_flip_signs(RDF_TO_LUF, k)[None, :, None]
        for j, name in enumerate(_sh_names(deg)):
            attrs[name] = rest[:, j].astype("<f4")
    rgba = np.concatenate([to_u8((a["sh_dc"] * SH_C0 + 0.5) * 255.0), to_u8(sigmoid(a["opacity"]) * 255.0)[:, None]], 1)
    attrs["COLOR_0"] = rgba
    blob, views, accessors, ids = bytearray(), [], [], {}
    for name, arr in attrs.items():
        data = np.ascontiguousarray(arr).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob += data + bytes(-len(data) % 4)
        comps = 1 if arr.ndim == 1 else arr.shape[1]
        acc = {"bufferView": len(views) - 1, "componentType": 5121 if arr.dtype == np.uint8 else 5126,
               "count": n, "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[comps]}
        if arr.dtype == np.uint8:
            acc["normalized"] = True
        if name == "POSITION":
            acc["min"], acc["max"] = arr.min(0).tolist(), arr.max(0).tolist()
        ids[name] = len(accessors)
        accessors.append(acc)
    doc = {"asset": {"version": "2.0", "generator": "ssgwarp"}, "extensionsUsed": [EXT],
           "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"mode": 0, "attributes": ids, "extensions": {EXT: {
               "kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
               "sortingMethod": "cameraDistance"}}}]}],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(js), JSON_CHUNK) + js
            + struct.pack("<II", len(blob), BIN_CHUNK) + bytes(blob))


def write_glb(path: str | Path, scene: GaussianScene) -> Path:
    """Write ``scene`` as a GLB with ``KHR_gaussian_splatting``, atomically."""
    return write_atomic(path, glb_bytes(scene))


def _chunks(data: bytes, where: str) -> tuple[dict, bytes]:
    if len(data) < 20:
        raise InputError(f"{where}: not a GLB file (too short)")
    magic, version, total = struct.unpack_from("<III", data)
    if magic != GLB_MAGIC:
        raise InputError(f"{where}: not a GLB file (no glTF magic)")
    if version != 2 or total > len(data):
        raise InputError(f"{where}: GLB version {version}, {total} bytes (expected version 2, at most the file's "
                         f"{len(data)} bytes)")
    off, js, blob = 12, None, b""
    while off + 8 <= total:
        length, kind = struct.unpack_from("<II", data, off)
        if length > total - off - 8:
            raise InputError(f"{where}: GLB chunk of {length} bytes runs past the file's end (truncated)")
        body = data[off + 8:off + 8 + length]
        if kind == JSON_CHUNK and js is None:
            js = body
        elif kind == BIN_CHUNK and not blob:
            blob = body
        off += 8 + length
    if js is None:
        raise InputError(f"{where}: GLB without a JSON chunk")
    try:
        doc = json.loads(js)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{where}: GLB JSON chunk is not JSON ({e})") from None
    if not isinstance(doc, dict):
        raise InputError(f"{where}: GLB JSON is not an object")
    return doc, blob


def read_glb(path: str | Path) -> GaussianScene:
    """Read the first ``KHR_gaussian_splatting`` primitive of a GLB file into a scene (RDF)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: GLB file not found")
    doc, blob = _chunks(path.read_bytes(), str(path))
    try:
        prims = [p for m in doc.get("meshes", []) for p in m.get("primitives", []) if EXT in p.get("extensions", {})]
    except (AttributeError, TypeError):
        prims = []
    if not prims:
        raise InputError(f"{path}: no mesh primitive with {EXT} (not a Gaussian splat glTF)")
    attrs = prims[0].get("attributes", {})
    nodes = doc.get("nodes", []) if isinstance(doc.get("nodes"), list) else []
    moved = [nd for nd in nodes if isinstance(nd, dict) and "mesh" in nd
             and any(k in nd for k in ("matrix", "translation", "rotation", "scale"))]
    if moved:
        raise InputError(f"{path}: the splats' node carries a transform, which is not applied here; re-export "
                         f"the glTF with the transform baked into the Gaussians")

    def accessor(name: str, comps: int):
        try:
            acc = doc["accessors"][attrs[name]]
            view = doc["bufferViews"][acc["bufferView"]]
            dtype, norm = _TYPES[acc["componentType"]]
            count, width = int(acc["count"]), _COMPONENTS[acc["type"]]
            start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
            stride = int(view.get("byteStride", 0)) or np.dtype(dtype).itemsize * width
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise InputError(f"{path}: accessor of {name} is missing or malformed ({type(e).__name__}: {e})") from None
        if "sparse" in acc or view.get("buffer", 0) != 0 or width != comps:
            raise InputError(f"{path}: {name}: sparse, external or {acc.get('type')} accessors are not read")
        item = np.dtype(dtype).itemsize * width
        if count <= 0 or stride < item or start < 0 or start + stride * (count - 1) + item > len(blob):
            raise InputError(f"{path}: {name} accessor reaches past the binary chunk (truncated or corrupt)")
        rows = np.lib.stride_tricks.as_strided(np.frombuffer(blob, np.uint8, len(blob) - start, start),
                                               (count, item), (stride, 1), writeable=False)
        out = np.ascontiguousarray(rows).view(dtype).reshape(count, width).astype(np.float64)
        if norm is not None:
            out = np.maximum(out / norm, -1.0) if acc.get("normalized") else out
        return out

    need = ["POSITION", f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY", f"{EXT}:SH_DEGREE_0_COEF_0"]
    missing = [a for a in need if a not in attrs]
    if missing:
        raise InputError(f"{path}: {EXT} primitive lacks {', '.join(missing)}")
    pos = accessor("POSITION", 3)
    n = len(pos)
    rot, scale = accessor(need[1], 4), accessor(need[2], 3)
    opac, dc = accessor(need[3], 1)[:, 0], accessor(need[4], 3)
    deg = 0
    while deg < 3 and all(nm in attrs for nm in _sh_names(deg + 1)):
        deg += 1
    rest = np.stack([accessor(nm, 3) for nm in _sh_names(deg)], 1) if deg else None
    if any(len(x) != n for x in (rot, scale, opac, dc, *([] if rest is None else [rest]))):
        raise InputError(f"{path}: {EXT} attributes have different counts")
    vals = [pos, rot, scale, opac, dc] + ([] if rest is None else [rest])
    if not all(np.isfinite(v).all() for v in vals):
        raise InputError(f"{path}: NaN/inf in the Gaussians' attributes")
    if (scale < 0).any() or (opac < 0).any() or (opac > 1).any():
        raise InputError(f"{path}: negative scales or opacities outside [0, 1] (invalid {EXT} values)")
    f = np.array(RDF_TO_LUF)
    quats = np.stack([rot[:, 3], rot[:, 0] * f[0], rot[:, 1] * f[1], rot[:, 2] * f[2]], 1)
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norm > 0, quats / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    if rest is not None:
        rest = rest * sh_flip_signs(RDF_TO_LUF, rest.shape[1])[None, :, None]
    log_scales = np.log(np.maximum(scale, np.exp(-30.0)))
    return arrays_scene(pos * f, log_scales, quats, logit(opac), dc, rest)
