"""Warp kernel launches from torch tensors at a small, fixed host cost per launch.

``wp.launch`` converts every argument on every call (type checks, one ctypes object per
argument, a fresh parameter block). The rasterizer launches the same few kernels with
arguments of the same types on every call, so this module records each launch once with
``wp.launch(..., record_cmd=True)`` (Warp's own argument packing, module loading and
checks) and then replays it: a :class:`_Plan` keeps one ctypes structure per kernel whose
fields are the kernel's parameters, refills it in one constructor call per launch and hands
it to the compiled kernel (CPU) or ``cuLaunchKernel`` through Warp's native launcher (CUDA),
on torch's current stream. Array arguments are Warp array descriptors built straight from a
tensor's pointer, shape and strides (:func:`arr`), with no ``wp.array`` in between.

Where Warp's internals differ from what this expects (another Warp version), every launch
falls back to ``wp.launch``; ``FAST`` says which path is in use.
"""
from __future__ import annotations

import ctypes
import math
import threading

import torch
import warp as wp

try:  # Warp 1.x internals: the array descriptor, the launch-bounds structure and the runtime
    from warp._src.types import array_t
    from warp._src import context as _wpc

    FAST = all(hasattr(_wpc, n) for n in ("runtime", "Launch")) and hasattr(array_t, "_fields_")
except ImportError:  # pragma: no cover - another Warp layout
    array_t, _wpc, FAST = None, None, False

NULL = array_t() if array_t is not None else None  # an absent array (null pointer)
INT32_MAX = 2**31 - 1
_INIT = False


def init() -> None:
    global _INIT
    if not _INIT:
        # keep Warp's per-module "load ... (compiled)" lines off the terminal; warnings still show
        wp.config.log_level = max(int(wp.config.log_level), int(wp.LOG_WARNING))
        wp.init()
        _INIT = True


# ---------------------------------------------------------------------------------------------
# array descriptors
# ---------------------------------------------------------------------------------------------
def arr(t: torch.Tensor, inner: int = 1):
    """1-D Warp array descriptor over a contiguous tensor, ``inner`` scalars per element (a Warp
    vector/matrix of that many components, or 1 for scalars). The tensor must stay alive until
    the launch has been queued."""
    es = t.element_size()
    return array_t(t.data_ptr(), 0, 1, (t.numel() // inner,), (es * inner,))


def rows(t: torch.Tensor, inner: int):
    """1-D descriptor of the rows of a 2-D view ``t [M, inner]`` whose rows are contiguous but may
    be spaced (e.g. a column block of a wider matrix)."""
    es = t.element_size()
    return array_t(t.data_ptr(), 0, 1, (t.shape[0],), (t.stride(0) * es,))


def grid(t: torch.Tensor, c: int, n: int, inner: int, per_camera: bool):
    """2-D descriptor ``[c, n]`` over a tensor of ``n`` (``per_camera=False``: camera stride 0,
    every camera reads the same element) or ``c * n`` contiguous elements of ``inner`` scalars.
    Kernels that read per-Gaussian inputs through it and write their adjoints into a contiguous
    ``[c, n]`` buffer get one adjoint slot per (camera, Gaussian) pair without copying the inputs."""
    es = t.element_size() * inner
    return array_t(t.data_ptr(), 0, 2, (c, n), ((n * es) if per_camera else 0, es))


def cams(t: torch.Tensor, c: int, n: int, inner: int):
    """2-D descriptor ``[c, n]`` over ``c`` contiguous per-camera elements (Gaussian stride 0)."""
    es = t.element_size() * inner
    return array_t(t.data_ptr(), 0, 2, (c, n), (es, 0))


def at(ptr: int, n: int, itemsize: int):
    """1-D descriptor of ``n`` elements of ``itemsize`` bytes at a raw device address."""
    return array_t(ptr, 0, 1, (n,), (itemsize,))


# ---------------------------------------------------------------------------------------------
# where launches go
# ---------------------------------------------------------------------------------------------
class Target:
    """A torch device (and on CUDA torch's current stream there) as Warp launch target."""

    __slots__ = ("key", "cpu", "device", "context", "stream")

    def __init__(self, key, device, stream):
        self.key = key
        self.device = device
        self.cpu = device.is_cpu
        self.context = None if self.cpu else device.context
        self.stream = stream  # raw CUDA stream handle (int), None on the CPU


_TARGETS: dict = {}
_raw_stream = getattr(torch._C, "_cuda_getCurrentRawStream", None)


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
        if key[0] == "cpu":
            tg = Target(key, wp.get_device("cpu"), None)
        else:
            tg = Target(key, wp.get_device(f"cuda:{key[0]}"), key[1])
        _TARGETS[key] = tg
    return tg


# ---------------------------------------------------------------------------------------------
# recorded launches
# ---------------------------------------------------------------------------------------------
class _Plan:
    """One kernel (forward or adjoint, one block size) on one device, recorded by Warp once and
    replayed with new arguments."""

    def __init__(self, kernel, tg: Target, dim: tuple, args: list, adj: list | None, block_dim):
        rec = wp.launch(kernel, dim=dim, inputs=args, adj_inputs=adj or [], adjoint=adj is not None,
                        device=tg.device, record_tape=False, record_cmd=True, block_dim=block_dim)
        self.kernel, self.block_dim = kernel, block_dim
        self.fast = FAST and isinstance(rec, _wpc.Launch) and len(dim) == kernel.adj.kernel_dim
        det = getattr(getattr(rec, "hooks", None), "det_launch_meta", None)
        if det is not None and getattr(det, "needs_deterministic", False):
            self.fast = False  # Warp's deterministic mode launches through its own path
        if not self.fast:
            return
        self.rec = rec  # keeps the loaded module alive
        n = len(args)
        params = rec.params
        field = lambda p: type(p)  # noqa: E731 - ctypes type of each packed parameter
        self.Args = type("Args", (ctypes.Structure,), {"_fields_": [(f"a{i}", field(p)) for i, p in enumerate(params[1:1 + n])]})
        self.args = self.Args()
        self.adj = None
        if adj is not None:
            self.Adj = type("Adj", (ctypes.Structure,),
                            {"_fields_": [(f"a{i}", field(p)) for i, p in enumerate(params[1 + n:])]})
            self.adj = self.Adj()
        bounds_fields = type(params[0])._fields_
        self.bounds = type("Bounds", (ctypes.Structure,), {"_fields_": bounds_fields})()
        self.ndim = len(dim)
        self.cpu = tg.cpu
        self.hook = rec.hooks.backward if adj is not None else rec.hooks.forward
        self.block = rec.block_dim
        if self.cpu:
            self.byref = (ctypes.byref(self.bounds), ctypes.byref(self.args)) + \
                ((ctypes.byref(self.adj),) if self.adj is not None else ())
        else:
            base = [ctypes.addressof(self.bounds)]
            for s in (self.args, self.adj):
                if s is not None:
                    base += [ctypes.addressof(s) + f[1].offset for f in
                             ((name, getattr(type(s), name)) for name, _ in type(s)._fields_)]
            self.addr = (ctypes.c_void_p * len(base))(*base)
            self.grid_stride = int(rec.grid_stride)
            self.cluster = int(rec.cluster_dim)
            self.smem = rec.hooks.backward_smem_bytes if adj is not None else rec.hooks.forward_smem_bytes
            self.cuda_launch = _wpc.runtime.core.wp_cuda_launch_kernel

    def run(self, tg: Target, dim: tuple, size: int, args: list, adj: list | None) -> None:
        if size > INT32_MAX or not self.fast:
            wp.launch(self.kernel, dim=dim, inputs=args, adj_inputs=adj or [], adjoint=adj is not None,
                      device=tg.device, stream=_stream(tg), record_tape=False, block_dim=self.block_dim)
            return
        self.args.__init__(*args)
        if adj is not None:
            self.adj.__init__(*adj)
        self.bounds.__init__(dim, size, 1)
        if self.cpu:
            if self.block > 1:
                core = _wpc.runtime.core
                core.wp_take_cpu_block_error()
                self.hook(*self.byref)
                err = core.wp_take_cpu_block_error()
                if err:
                    raise RuntimeError(f"Error launching kernel '{self.kernel.key}' on the CPU: "
                                       f"{err.decode('utf-8', errors='replace')}")
            else:
                self.hook(*self.byref)
        elif self.cuda_launch(tg.context, self.hook, size, 0, self.block, self.grid_stride, self.cluster, self.smem,
                              self.addr, tg.stream, None):
            raise RuntimeError(f"Error launching kernel '{self.kernel.key}' on {tg.device}: "
                               f"{_wpc.runtime.get_error_string()}")


_LOCAL = threading.local()  # plans per thread: a plan's argument block is filled, then launched


def launch(kernel, dim, args: list, tg: Target, adj: list | None = None, block_dim: int | None = None) -> None:
    """Launch ``kernel`` over ``dim`` (int or tuple) with ``args`` (its parameters in order: array
    descriptors, :data:`NULL` for an absent array, Python numbers for scalars) on ``tg``; with
    ``adj`` (the adjoint parameters) its adjoint. Launches of no threads are skipped."""
    if type(dim) is int:
        dim = (dim,)
    size = math.prod(dim)
    if size == 0:
        return
    plans = getattr(_LOCAL, "plans", None)
    if plans is None:
        plans = _LOCAL.plans = {}
    key = (kernel, tg.key, adj is not None, block_dim)
    plan = plans.get(key)
    if plan is None:
        plan = plans[key] = _Plan(kernel, tg, dim, args, adj, block_dim)
    plan.run(tg, dim, size, args, adj)


_STREAMS: dict = {}


def _stream(tg: Target):
    """Warp's wrapper of the target's CUDA stream (for the ``wp.launch`` fall-back)."""
    if tg.cpu:
        return None
    ws = _STREAMS.get(tg.key)
    if ws is None:
        ws = _STREAMS[tg.key] = wp.Stream(tg.device, cuda_stream=tg.stream)
    return ws


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int, tg: Target) -> None:
    """Stable radix sort of ``count`` int64 ``keys`` with their 4-byte ``values`` over key bits
    ``[0, end_bit)``, in place (both tensors hold ``2 * count`` elements: the upper halves are
    scratch), on the target's stream."""
    if count == 0:
        return
    if not FAST:
        ka = wp.from_torch(keys, dtype=wp.int64)
        va = wp.from_torch(values, dtype=wp.int32)
        with wp.ScopedDevice(tg.device), wp.ScopedStream(_stream(tg)):
            wp.utils.radix_sort_pairs(ka, va, count, 0, end_bit)
        return
    core = _wpc.runtime.core
    if tg.cpu:
        core.wp_radix_sort_pairs_int64_host(keys.data_ptr(), values.data_ptr(), count, 0, end_bit, 4)
        return
    # Warp's device sort runs on the device's current Warp stream: point it at torch's for the call
    saved = tg.device.stream.cuda_stream
    core.wp_cuda_context_set_stream(tg.context, tg.stream, 0)
    try:
        core.wp_radix_sort_pairs_int64_device(keys.data_ptr(), values.data_ptr(), count, 0, end_bit, 4)
    finally:
        core.wp_cuda_context_set_stream(tg.context, saved, 0)
