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
