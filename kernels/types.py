"""Vector/matrix types of one precision (float32 or float64) for the kernel factories."""

import functools
from types import SimpleNamespace

import warp as wp


@functools.lru_cache(maxsize=None)
def types_for(scalar) -> SimpleNamespace:
    """Namespace of ``scalar``, ``vec2``, ``vec3``, ``vec4``, ``mat22``, ``mat33``, ``mat44``, ``mat23``
    and ``splat`` (a projected Gaussian packed as x, y, conic a, b, c, opacity)."""
    return SimpleNamespace(
        scalar=scalar,
        vec2=wp.types.vector(2, scalar),
        vec3=wp.types.vector(3, scalar),
        vec4=wp.types.vector(4, scalar),
        mat22=wp.types.matrix((2, 2), scalar),
        mat33=wp.types.matrix((3, 3), scalar),
        mat44=wp.types.matrix((4, 4), scalar),
        mat23=wp.types.matrix((2, 3), scalar),
        splat=wp.types.vector(6, scalar),  # one projected Gaussian: x, y, conic a, b, c, opacity
    )


@functools.lru_cache(maxsize=None)
def channel_vector(scalar, channels: int):
    """The ``channels``-long vector type blending accumulates per pixel."""
    return wp.types.vector(channels, scalar)


_SPLAT32 = types_for(wp.float32).splat
_SPLAT64 = types_for(wp.float64).splat
# a plain pointer read: no negative-index wrap and no strided 64-bit address arithmetic, which
# the blending loops would otherwise pay on every Gaussian they visit; on CUDA three 8-byte
# (float32) or 16-byte (float64) loads instead of six scalar ones (a splat is 24 or 48 bytes, so
# every element of a contiguous array is aligned for them)
_LOAD32 = """
#if defined(__CUDA_ARCH__)
const float2* p = reinterpret_cast<const float2*>(a.data + k);
const float2 u = p[0], v = p[1], w = p[2];
wp::vec_t<6, float> r;
r.c[0] = u.x; r.c[1] = u.y; r.c[2] = v.x; r.c[3] = v.y; r.c[4] = w.x; r.c[5] = w.y;
return r;
#else
return a.data[k];
#endif
"""
_LOAD64 = _LOAD32.replace("float2", "double2").replace("<6, float>", "<6, double>")


@wp.func_native(_LOAD32)
def splat_at(a: wp.array(dtype=_SPLAT32), k: int) -> _SPLAT32:
    """``a[k]`` for a contiguous array of packed splats with ``0 <= k < len(a)`` (unchecked)."""
    ...


@wp.func_native(_LOAD64)
def splat_at(a: wp.array(dtype=_SPLAT64), k: int) -> _SPLAT64:  # noqa: F811 (the float64 overload)
    """``a[k]`` for a contiguous array of packed splats with ``0 <= k < len(a)`` (unchecked)."""
    ...


@functools.lru_cache(maxsize=None)
def element_at(dtype):
    """``element_at(a, k)``: ``a[k]`` for a contiguous array of ``dtype`` with ``0 <= k < len(a)``
    (unchecked): a plain pointer read, without the negative-index wrap and the strided 64-bit
    address arithmetic of ``a[k]``, for the per-intersection colours the blending loops read."""

    @wp.func_native("return a.data[k];")
    def element_at(a: wp.array(dtype=dtype), k: int) -> dtype:
        ...

    return element_at
