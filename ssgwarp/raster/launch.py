"""Warp kernel launches from torch tensors at a small, fixed host cost per launch.

``wp.launch`` converts every argument on every call (type checks, one ctypes object per
argument, a fresh parameter block). The rasterizer launches the same few kernels with
arguments of the same types on every call, so this module records each launch once with
``wp.launch(..., record_cmd=True)`` (Warp's own module loading, argument packing and checks)
and then replays it: a :class:`_Plan` keeps one parameter buffer per kernel, laid out as Warp's
ctypes structures (launch bounds, arguments, adjoint arguments), refills it with one
``struct.pack_into`` per launch and hands it to the compiled kernel (CPU) or to Warp's native
CUDA launcher on torch's current stream. Array arguments are the 12 fields of a Warp array
descriptor built straight from a tensor's pointer, shape and strides (:func:`arr`, spliced into
the argument list), with no ``wp.array`` in between. Measured per launch of a 33-parameter
kernel: 8 µs on the CPU and 18 µs on CUDA, against 49 and 93 µs through ``wp.launch``
(docs/notes/benchmarks-history.md).

Every use of Warp's and torch's private APIs (the replay itself, Warp's native calls, torch's direct autograd
entry) lives in :mod:`ssgwarp.raster.private_api`, behind its version gate and self-test; where they are not
usable, every launch goes through ``wp.launch`` (same results); ``FAST`` says whether they may be tried.
"""
from __future__ import annotations

import ctypes
import math
import threading

import torch
import warp as wp

from . import private_api as P

FAST = P.AVAILABLE   # (per device, the self-test decides too: Target.fast)
INT32_MAX = 2**31 - 1
_INIT = False


def init() -> None:
    global _INIT
    if not _INIT:
        # keep Warp's per-module "load ... (compiled)" lines off the terminal; warnings still show
        wp.config.log_level = max(int(wp.config.log_level), int(wp.LOG_WARNING))
        from ..core.native_stderr import captured, replay

        with captured() as said:  # its native "could not load the NVIDIA CUDA driver" on CPU machines: dropped
            wp.init()
        replay(said, drop=[r"Could not find or load the NVIDIA CUDA driver"])
        _INIT = True


# ---------------------------------------------------------------------------------------------
# array descriptors: the 12 fields of Warp's array_t (data, grad, shape[4], strides[4], ndim,
# flags) as a tuple, which launches splice into their argument list (``*arr(t)``)
# ---------------------------------------------------------------------------------------------
NULL = (0,) * 12  # an absent array (null pointer, shape 0)


_ITEMSIZE: dict = {}  # bytes per element of each dtype seen (a dict lookup is cheaper than element_size())


def _itemsize(t: torch.Tensor) -> int:
    try:
        return _ITEMSIZE[t.dtype]
    except KeyError:
        es = _ITEMSIZE[t.dtype] = t.element_size()
        return es


def arr(t: torch.Tensor, inner: int = 1) -> tuple:
    """1-D Warp array over a contiguous tensor, ``inner`` scalars per element (a Warp
    vector/matrix of that many components, or 1 for scalars). The tensor must stay alive until
    the launch has been queued."""
    try:
        es = _ITEMSIZE[t.dtype]
    except KeyError:
        es = _ITEMSIZE[t.dtype] = t.element_size()
    return (t.data_ptr(), 0, t.numel() // inner, 0, 0, 0, es * inner, 0, 0, 0, 1, 0)


def rows(t: torch.Tensor, inner: int) -> tuple:
    """1-D Warp array over the rows of a 2-D view ``t [M, inner]`` whose rows are contiguous but
    may be spaced (e.g. a column block of a wider matrix)."""
    return (t.data_ptr(), 0, t.shape[0], 0, 0, 0, t.stride(0) * t.element_size(), 0, 0, 0, 1, 0)


def grid(t: torch.Tensor, c: int, n: int, inner: int, per_camera: bool) -> tuple:
    """2-D Warp array ``[c, n]`` over a tensor of ``n`` (``per_camera=False``: camera stride 0,
    every camera reads the same element) or ``c * n`` contiguous elements of ``inner`` scalars.
    Kernels that read per-Gaussian inputs through it and write their adjoints into a contiguous
    ``[c, n]`` buffer get one adjoint slot per (camera, Gaussian) pair without copying the inputs."""
    es = t.element_size() * inner
    return (t.data_ptr(), 0, c, n, 0, 0, (n * es) if per_camera else 0, es, 0, 0, 2, 0)


def cams(t: torch.Tensor, c: int, n: int, inner: int) -> tuple:
    """2-D Warp array ``[c, n]`` over ``c`` contiguous per-camera elements (Gaussian stride 0)."""
    return (t.data_ptr(), 0, c, n, 0, 0, t.element_size() * inner, 0, 0, 0, 2, 0)


def grid3(t: torch.Tensor, c: int, n: int, k: int, inner: int, per_camera: bool) -> tuple:
    """3-D Warp array ``[c, n, k]`` over ``n`` (camera stride 0) or ``c * n`` contiguous rows of
    ``k`` elements of ``inner`` scalars (e.g. SH coefficients)."""
    es = t.element_size() * inner
    return (t.data_ptr(), 0, c, n, k, 0, (n * k * es) if per_camera else 0, k * es, es, 0, 3, 0)


def at(ptr: int, n: int, itemsize: int) -> tuple:
    """1-D Warp array of ``n`` elements of ``itemsize`` bytes at a raw address."""
    return (ptr, 0, n, 0, 0, 0, itemsize, 0, 0, 0, 1, 0)


class _NoBackward:
    """What a Function's forward is handed for a context when no backward can follow: what it
    records for the backward (attributes, saved tensors) goes nowhere."""

    def save_for_backward(self, *tensors) -> None:
        pass

    def mark_non_differentiable(self, *tensors) -> None:
        pass

    def set_materialize_grads(self, value: bool) -> None:
        pass


def apply(fn, *args, needs_grad: bool | None = None):
    """``fn.apply(*args)`` for an autograd Function without the per-call Python of
    ``torch.autograd.Function.apply`` (argument binding, functorch unwrapping), which only matters
    under functorch transforms: those still go through ``fn.apply`` (so does a torch without the
    private entry point). Where no backward can follow (gradients off, or no tensor argument
    requires one), ``fn.forward`` runs on its own, without an autograd node: the same outputs,
    which then need no gradient either way. ``needs_grad``: whether a backward can follow, where
    the caller knows it already (else found from ``args``)."""
    entry = P.function_apply(fn)
    if entry is None:
        return fn.apply(*args)
    if needs_grad is None:
        needs_grad = torch.is_grad_enabled() and any(isinstance(a, torch.Tensor) and a.requires_grad for a in args)
    if not needs_grad:
        return fn.forward(_NoBackward(), *args)
    return entry(*args)


# ---------------------------------------------------------------------------------------------
# what kernels read: precision, fast maths, dense tensors, incoming gradients
# ---------------------------------------------------------------------------------------------
def scalar_of(dtype: torch.dtype):
    """The Warp scalar type of a torch float dtype (the kernels are built for float32 and float64)."""
    if dtype == torch.float32:
        return wp.float32
    if dtype == torch.float64:
        return wp.float64
    raise ValueError(f"ssgwarp kernels support float32 and float64, got {dtype}")


def fast_math(settings, scalar) -> bool:
    """Fast maths (approximate exp, log, division, square roots) in the CUDA kernels: float32 only
    (a CUDA compile option; the CPU build ignores it)."""
    return bool(settings.fast_math) and scalar == wp.float32


def dense(t: torch.Tensor) -> torch.Tensor:
    """``t`` itself when contiguous, else a contiguous copy (outside autograd): what kernels read."""
    return t if t.is_contiguous() else t.detach().contiguous()


def grad_rows(g, inner: int, n: int):
    """``(descriptor, tensor)`` of an incoming gradient read as ``n`` rows of ``inner`` values
    (row-strided views, e.g. column blocks of the blending's packed gradients, are read in place);
    :data:`NULL` when there is none. Keep the tensor alive until the launch is queued."""
    if g is None:
        return NULL, None
    if g.is_contiguous():  # (a gradient of its own: no view needed)
        return arr(g, inner), g
    # a column block of a wider buffer (the blending backward's packed rows: the usual case), read
    # where it lies when its rows are evenly spaced: no torch call
    st, shape = g.stride(), g.shape
    lead = len(shape) - (1 if inner > 1 else 0)
    if lead >= 1 and (inner == 1 or (st[-1] == 1 and shape[-1] == inner)) and all(
            shape[d] == 1 or st[d] == st[d + 1] * shape[d + 1] for d in range(lead - 1)):
        return (g.data_ptr(), 0, n, 0, 0, 0, st[lead - 1] * _itemsize(g), 0, 0, 0, 1, 0), g
    g = g.reshape(n, inner)  # (a view where it can be; the kernels read the values, not the graph)
    if g.stride(1) != 1 and inner > 1:
        g = g.contiguous()
    return rows(g, inner), g


def pixel_rows(g, inner: int):
    """``(descriptor, tensor)`` of an image's incoming gradient ``g [..., inner]`` read as one row
    of ``inner`` scalars per pixel, in place over its own strides where its pixel axes merge into
    one (contiguous; expanded from a scalar, as the gradient of ``image.sum()`` is; channels first
    in one camera): a 2-D scalar descriptor ``[pixels, inner]``, 1-D ``[pixels]`` for ``inner =
    1``; else over a contiguous copy. :data:`NULL` when there is none. Keep the tensor alive until
    the launch is queued."""
    if g is None:
        return NULL, None
    if g.is_contiguous():  # (the usual case: rows of ``inner`` values, no view needed)
        es = _itemsize(g)
        if inner == 1:
            return (g.data_ptr(), 0, g.numel(), 0, 0, 0, es, 0, 0, 0, 1, 0), g
        return (g.data_ptr(), 0, g.numel() // inner, inner, 0, 0, inner * es, es, 0, 0, 2, 0), g
    try:
        v = g.view(-1, inner)
    except RuntimeError:  # (pixel axes that do not merge: copied)
        g = g.contiguous()
        v = g.view(-1, inner)
    es = v.element_size()
    sp, sc = v.stride()
    if inner == 1:
        return (v.data_ptr(), 0, v.shape[0], 0, 0, 0, sp * es, 0, 0, 0, 1, 0), g
    return (v.data_ptr(), 0, v.shape[0], inner, 0, 0, sp * es, sc * es, 0, 0, 2, 0), g


# ---------------------------------------------------------------------------------------------
# where launches go
# ---------------------------------------------------------------------------------------------
class Target:
    """A torch device (and on CUDA torch's current stream there) as Warp launch target."""

    __slots__ = ("key", "dkey", "cpu", "device", "device_torch", "context", "stream", "primary", "fast")

    def __init__(self, key, device, stream):
        self.key = key
        self.dkey = key[0]  # the device alone (recorded launches do not depend on the stream)
        self.device = device
        self.device_torch = torch.device("cpu") if key[0] == "cpu" else torch.device("cuda", key[0])
        self.cpu = device.is_cpu
        self.context = None if self.cpu else device.context
        self.primary = self.cpu or bool(getattr(device, "is_primary", False))
        self.stream = stream  # raw CUDA stream handle (int), None on the CPU
        self.fast = False     # whether launches here take the private fast path (set by target())


_TARGETS: dict = {}
_STREAMS: dict = {}  # Warp's wrappers of torch's streams, for the wp.launch fall-back
_raw_stream = P.raw_stream


def target(t: torch.Tensor) -> Target:
    """The launch target of tensor ``t``'s device (CUDA: torch's current stream on it)."""
    dev = t.device
    if dev.type == "cpu":
        key = ("cpu", 0)
    elif dev.type == "cuda":
        idx = dev.index if dev.index is not None else torch.cuda.current_device()
        stream = _raw_stream(idx) if _raw_stream is not None else torch.cuda.current_stream(idx).cuda_stream
        key = (idx, stream)
    else:
        raise ValueError(f"ssgwarp kernels run on CPU or CUDA tensors, got {dev}")
    tg = _TARGETS.get(key)
    if tg is None:
        init()
        if len(_TARGETS) > 64:  # (a program that makes a new stream per call: keep the cache small)
            _TARGETS.clear()
            _STREAMS.clear()
        if key[0] == "cpu":
            tg = Target(key, wp.get_device("cpu"), None)
        else:
            tg = Target(key, wp.get_device(f"cuda:{key[0]}"), key[1])
        tg.fast = FAST and P.fast_path_works(tg, _stream(tg))
        _TARGETS[key] = tg
    return tg


# ---------------------------------------------------------------------------------------------
# recorded launches
# ---------------------------------------------------------------------------------------------
class _Plan:
    """One kernel (forward or adjoint, one block size) on one device: replayed through
    :class:`ssgwarp.raster.private_api.Replay` where the target allows it, else launched with ``wp.launch``."""

    def __init__(self, kernel, tg: Target, dim: tuple, args: list, adj: list | None, block_dim):
        self.kernel, self.block_dim = kernel, block_dim
        self.fast = P.Replay.record(kernel, tg, dim, args, adj, block_dim) if FAST and tg.fast else None

    def run(self, tg: Target, dim: tuple, size: int, args: list, adj: list | None) -> None:
        if size > INT32_MAX or self.fast is None:
            wp.launch(self.kernel, dim=dim, inputs=P.warp_args(self.kernel, args, tg.device),
                      adj_inputs=P.warp_args(self.kernel, adj, tg.device) if adj is not None else [],
                      adjoint=adj is not None, device=tg.device, stream=_stream(tg), record_tape=False,
                      block_dim=self.block_dim)
            return
        self.fast.run(tg, dim, size, args, adj)


_LOCAL = threading.local()  # plans per thread: a plan's parameter buffer is filled, then launched
_RECORD = threading.Lock()  # one recording at a time (Warp's module loading is not made for threads)


def launch(kernel, dim, args: list, tg: Target, adj: list | None = None, block_dim: int | None = None) -> None:
    """Launch ``kernel`` over ``dim`` (int or tuple of the kernel's dimensions) on ``tg``.

    ``args``: the kernel's parameters in order, flat: each array as the 12 values of a descriptor
    spliced in (``*arr(t)``, ``*NULL`` for an absent array), scalars as Python numbers. With
    ``adj`` (the adjoint parameters, the same way) the kernel's adjoint runs. Launches of no
    threads are skipped."""
    if type(dim) is int:
        dim = (dim,)
    size = math.prod(dim)
    if size == 0:
        return
    plans = getattr(_LOCAL, "plans", None)
    if plans is None:
        plans = _LOCAL.plans = {}
    key = (kernel, tg.dkey, adj is not None, block_dim)
    plan = plans.get(key)
    if plan is None:
        with _RECORD:
            plan = plans[key] = _Plan(kernel, tg, dim, args, adj, block_dim)
    plan.run(tg, dim, size, args, adj)


def _stream(tg: Target):
    """Warp's wrapper of the target's CUDA stream (for the ``wp.launch`` fall-back)."""
    if tg.cpu:
        return None
    ws = _STREAMS.get(tg.key)
    if ws is None:
        ws = _STREAMS[tg.key] = wp.Stream(tg.device, cuda_stream=tg.stream)
    return ws


def zeros(shape: tuple, dtype: torch.dtype, tg: Target) -> torch.Tensor:
    """``torch.zeros(shape)`` on the target's device: on CUDA an uninitialised tensor cleared by one
    ``cudaMemsetAsync`` on the target's stream (Warp's native call: one call instead of torch's fill
    kernel and its dispatch, what a backward's gradient buffer costs on every training step)."""
    if tg.cpu or not (FAST and tg.fast) or not tg.primary:
        return torch.zeros(shape, dtype=dtype, device=tg.device_torch)
    t = torch.empty(shape, dtype=dtype, device=tg.device_torch)
    n = t.numel() * _itemsize(t)
    if n:
        P.memset(tg, t.data_ptr(), n)
    return t


_PINNED = threading.local()  # per thread: a pinned host int64 that read-backs land in


def read_int64(t: torch.Tensor, index: int, tg: Target) -> int:
    """``int(t[index])`` of a contiguous int64 tensor once the target's queued work has written it:
    on CUDA one 8-byte copy into pinned host memory on the target's stream, then a wait for that
    stream (the call's one synchronisation); on the CPU the value in place (launches there have
    finished when they return). No torch call either way. :func:`start_read_int64` and
    :func:`finish_read_int64` are its two halves, for host work in between."""
    return finish_read_int64(start_read_int64(t, index, tg), tg)


def start_read_int64(t: torch.Tensor, index: int, tg: Target):
    """The first half of :func:`read_int64`: queues the copy of ``t[index]`` (CUDA) and returns at
    once; hand what it returns to :func:`finish_read_int64` (one read at a time per thread)."""
    if tg.cpu:
        return ctypes.c_int64.from_address(t.data_ptr() + 8 * index).value
    if not (FAST and tg.fast) or not tg.primary:
        return t[index:index + 1].clone()  # (the value as the stream has it now; read in the second half)
    host = getattr(_PINNED, "buf", None)
    if host is None:
        host = _PINNED.buf = torch.empty(1, dtype=torch.int64, pin_memory=True)
    P.copy_to_host(tg, host.data_ptr(), t.data_ptr() + 8 * index, 8)
    return host


def finish_read_int64(pending, tg: Target) -> int:
    """The value :func:`start_read_int64` queued, once it has arrived (waits for the target's stream)."""
    if tg.cpu:
        return pending
    if not (FAST and tg.fast) or not tg.primary:
        return int(pending.item())
    P.synchronize(tg)
    return ctypes.c_int64.from_address(pending.data_ptr()).value


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int, tg: Target) -> None:
    """Stable radix sort of the first ``count`` int64 ``keys`` with their 4-byte ``values`` over key
    bits ``[0, end_bit)``, in place (both tensors hold at least ``2 * count`` elements: the next
    ``count`` are scratch), on the target's stream."""
    if count == 0:
        return
    if not (FAST and tg.fast) or not tg.primary:
        P.sort_pairs_public(keys, values, count, end_bit, tg, _stream(tg))
        return
    P.sort_pairs_int64(keys, values, count, end_bit, tg)
