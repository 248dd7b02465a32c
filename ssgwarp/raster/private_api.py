"""Every use of Warp's and torch's private APIs, in this one module, behind an explicit version gate and a
behavioural self-test.

The hot path takes a few shortcuts through internals that neither library promises to keep:

* Warp (``warp._src``): a recorded launch (``wp.launch(..., record_cmd=True)``) replayed by refilling its
  parameter block with one ``struct.pack_into`` and calling the compiled CPU kernel, or Warp's native CUDA
  launcher (``wp_cuda_launch_kernel``) on torch's stream, directly (:class:`Replay`); the native clear, 8-byte
  read-back, stream wait and radix sort (``wp_memset_device``, ``wp_memcpy_d2h``, ``wp_cuda_stream_synchronize``,
  ``wp_radix_sort_pairs_int64_*``);
* torch: ``torch._C._FunctionBase.apply`` (an autograd Function entered without ``Function.apply``'s Python),
  ``torch._C._cuda_getCurrentRawStream``, and the fused Adam step (``torch._fused_adam_``, ``torch._foreach_*``)
  without ``Adam.step``'s per-group Python.

Each has a public path that gives the same numbers (``wp.launch``, ``wp.utils.radix_sort_pairs``, torch calls,
``Function.apply``, ``Adam.step``). A shortcut is taken only where (1) the installed Warp lies in the range this
module was written for (:data:`WARP_SUPPORTED`, pyproject.toml's ``warp-lang>=1.19,<2``), (2) the names it
uses exist, and (3) its self-test passed: at the first use on a device, a probe kernel (``kernels/probe.py``:
vector arrays, a stride-0 2-D array, a ``wp.struct``, a scalar) is launched forward and adjoint through the
replay and through ``wp.launch`` and the outputs compared bit for bit, likewise the sort (and on CUDA the clear
and the read-back); the autograd entry and the fused Adam step are each checked once against torch's public
calls. Where a check disagrees or fails, a warning says so once and the public path is used from then on.
"""
from __future__ import annotations

import ctypes
import re
import struct
import threading
import warnings

import torch
import warp as wp

# -- the version gate ---------------------------------------------------------------------------------------
WARP_SUPPORTED = ((1, 19), (2, 0))   # [from, below): the warp-lang versions whose internals this module knows


def version_tuple(text: str) -> tuple:
    """``"1.19.0"`` -> ``(1, 19, 0)`` (a suffix such as ``.dev0`` or ``rc1`` ignored)."""
    return tuple(int(m) for m in re.findall(r"\d+", text.split("+")[0])[:3])


def in_supported_range(version: tuple) -> bool:
    return WARP_SUPPORTED[0] <= tuple(version[:2]) < WARP_SUPPORTED[1]


WARP_VERSION = version_tuple(wp.config.version)
try:
    from warp._src.types import array_t
    from warp._src import context as _wpc

    _NAMES = all(hasattr(_wpc, n) for n in ("runtime", "Launch")) and hasattr(array_t, "_fields_")
except ImportError:  # pragma: no cover - another Warp layout
    array_t, _wpc, _NAMES = None, None, False
# whether the Warp shortcuts may be tried at all (each device's self-test decides then)
AVAILABLE = in_supported_range(WARP_VERSION) and _NAMES

_LOCK = threading.Lock()
_WARNED: set = set()


def _warn(what: str, why) -> None:
    if what not in _WARNED:
        _WARNED.add(what)
        warnings.warn(f"ssgwarp: {what} did not pass its self-test ({why}); the public path is used instead "
                      f"(same results, more host time). warp-lang {wp.config.version}, torch {torch.__version__}",
                      RuntimeWarning, stacklevel=3)


# -- a kernel's parameters --------------------------------------------------------------------------------
def kernel_params(kernel) -> list:
    """The kernel's parameters (name, type) in order."""
    return kernel.adj.args


def kernel_dim(kernel) -> int:
    return kernel.adj.kernel_dim


def _is_struct_type(t) -> bool:
    """Whether a kernel parameter's type is a ``wp.struct`` (its fields and ctypes layout)."""
    return hasattr(t, "vars") and hasattr(t, "ctype") and hasattr(t, "instance_type")


def warp_args(kernel, flat: list, device) -> list:
    """The ``wp.launch`` arguments of a flat argument list (each array as the 12 values of a Warp array
    descriptor, ``(data, grad, shape[4], strides[4], ndim, flags)``, spliced in; a ``wp.struct`` as its fields in
    order): ``wp.array`` views of the same memory (None for a null descriptor), struct instances, scalars."""
    def view(a, d, nd):
        return None if d[0] == 0 else wp.array(ptr=d[0], dtype=a.type.dtype, shape=tuple(d[2:2 + nd]),
                                               strides=tuple(d[6:6 + nd]), device=device)

    return _unflatten(kernel, flat, view)


def _descriptor_args(kernel, flat: list) -> list:
    """As :func:`warp_args`, with arrays as Warp's own descriptors (what a recorded launch packs)."""
    return _unflatten(kernel, flat, lambda a, v, nd: array_t(v[0], v[1], nd, v[2:2 + nd], v[6:6 + nd], v[11]))


def _unflatten(kernel, flat: list, array) -> list:
    """``kernel``'s arguments from a flat list: each array's 12 descriptor values through ``array(param, values,
    ndim)``, a ``wp.struct`` from its fields in order, scalars as they are; a list of another length than the
    parameters take is a TypeError."""
    out, i = [], 0
    for a in kernel_params(kernel):
        if wp.types.is_array(a.type):
            d = flat[i:i + 12]
            out.append(array(a, d, d[10]))
            i += 12
        elif _is_struct_type(a.type):
            inst = a.type()
            for name in a.type.vars:
                setattr(inst, name, flat[i])
                i += 1
            out.append(inst)
        else:
            out.append(flat[i])
            i += 1
    if i != len(flat):
        raise TypeError(f"internal: {len(flat)} values for the arguments of kernel '{kernel.key}'")
    return out


# -- recorded launches, replayed ----------------------------------------------------------------------------
_CODES = {ctypes.c_int8: "b", ctypes.c_uint8: "B", ctypes.c_int16: "h", ctypes.c_uint16: "H", ctypes.c_int32: "i",
          ctypes.c_uint32: "I", ctypes.c_int64: "q", ctypes.c_uint64: "Q", ctypes.c_float: "f",
          ctypes.c_double: "d", ctypes.c_bool: "?"}


def layout(ctype) -> str | None:
    """``struct`` format (native byte order, explicit padding) of a ctypes scalar, array or
    structure, laid out as ctypes lays it out; None for anything else."""
    if ctype in _CODES:
        return _CODES[ctype]
    for base, code in _CODES.items():  # ctypes aliases (c_long, c_size_t, ...)
        if ctypes.sizeof(ctype) == ctypes.sizeof(base) and getattr(ctype, "_type_", None) == getattr(base, "_type_", 0):
            return code
    if issubclass(ctype, ctypes.Array):
        inner = layout(ctype._type_)
        return None if inner is None else inner * ctype._length_
    if issubclass(ctype, ctypes.Structure):
        out, pos = "", 0
        for name, ft in ctype._fields_:
            off = getattr(ctype, name).offset
            f = layout(ft)
            if f is None:
                return None
            out += "x" * (off - pos) + f
            pos = off + ctypes.sizeof(ft)
        return out + "x" * (ctypes.sizeof(ctype) - pos)
    return None


class Replay:
    """One kernel (forward or adjoint, one block size) on one device, recorded by Warp once and replayed: its
    parameters (launch bounds, arguments, adjoint arguments) live in one buffer that one ``struct.pack_into``
    refills per launch; the compiled kernel reads them in place. ``tg``: the launch target (``device``, ``cpu``,
    ``context``, ``stream``: ``ssgwarp.raster.launch.Target``)."""

    @classmethod
    def record(cls, kernel, tg, dim: tuple, args: list, adj: list | None, block_dim) -> "Replay | None":
        """The replay of this launch, or None where Warp's recorded launch is not the expected one."""
        nargs = len(kernel_params(kernel))
        rec = wp.launch(kernel, dim=dim, inputs=_descriptor_args(kernel, args),
                        adj_inputs=_descriptor_args(kernel, adj) if adj is not None else [], adjoint=adj is not None,
                        device=tg.device, record_tape=False, record_cmd=True, block_dim=block_dim)
        det = getattr(getattr(rec, "hooks", None), "det_launch_meta", None)
        if not (isinstance(rec, _wpc.Launch) and len(dim) == kernel_dim(kernel)
                and not (det is not None and getattr(det, "needs_deterministic", False))):
            return None
        params = rec.params  # [bounds, forward args..., adjoint args...] as Warp packed them
        blocks = [type(params[0])._fields_, [(f"a{i}", type(p)) for i, p in enumerate(params[1:1 + nargs])]]
        if adj is not None:
            blocks.append([(f"a{i}", type(p)) for i, p in enumerate(params[1 + nargs:])])
        structs = [type(f"P{j}", (ctypes.Structure,), {"_fields_": f}) for j, f in enumerate(blocks)]
        fmts = [layout(st) for st in structs]
        if any(f is None for f in fmts):
            return None
        return cls(kernel, tg, rec, structs, fmts, adj is not None)

    def __init__(self, kernel, tg, rec, structs, fmts, adjoint: bool):
        self.kernel = kernel
        self.rec = rec  # keeps the loaded module alive
        # one buffer: each block at a 16-byte aligned offset
        offs, pos = [], 0
        for st in structs:
            pos = -(-pos // 16) * 16
            offs.append(pos)
            pos += ctypes.sizeof(st)
        self.buf = ctypes.create_string_buffer(max(pos, 16))
        base = ctypes.addressof(self.buf)
        fmt = "="  # (the padding is explicit)
        cur = 0
        for off, f, st in zip(offs, fmts, structs):
            fmt += "x" * (off - cur) + f
            cur = off + ctypes.sizeof(st)
        self.pack = struct.Struct(fmt).pack_into
        self.cpu = tg.cpu
        self.hook = rec.hooks.backward if adjoint else rec.hooks.forward
        self.block = rec.block_dim
        if self.cpu:
            self.ptrs = tuple(ctypes.c_void_p(base + o) for o in offs)
        else:
            addrs = [base + offs[0]]
            for st, off in zip(structs[1:], offs[1:]):
                addrs += [base + off + getattr(st, name).offset for name, _ in st._fields_]
            self.addr = (ctypes.c_void_p * len(addrs))(*addrs)
            self.grid_stride = int(rec.grid_stride)
            self.cluster = int(rec.cluster_dim)
            self.smem = rec.hooks.backward_smem_bytes if adjoint else rec.hooks.forward_smem_bytes
            self.cuda_launch = _wpc.runtime.core.wp_cuda_launch_kernel

    def run(self, tg, dim: tuple, size: int, args: list, adj: list | None) -> None:
        if adj is None:
            self.pack(self.buf, 0, *dim, size, 1, *args)
        else:
            self.pack(self.buf, 0, *dim, size, 1, *args, *adj)
        if self.cpu:
            if self.block > 1:
                core = _wpc.runtime.core
                core.wp_take_cpu_block_error()
                self.hook(*self.ptrs)
                err = core.wp_take_cpu_block_error()
                if err:
                    raise RuntimeError(f"Error launching kernel '{self.kernel.key}' on the CPU: "
                                       f"{err.decode('utf-8', errors='replace')}")
            else:
                self.hook(*self.ptrs)
        elif self.cuda_launch(tg.context, self.hook, size, 0, self.block, self.grid_stride, self.cluster, self.smem,
                              self.addr, tg.stream, None):
            raise RuntimeError(f"Error launching kernel '{self.kernel.key}' on {tg.device}: "
                               f"{_wpc.runtime.get_error_string()}")


# -- Warp's native runtime calls (CUDA: on the target's stream) ----------------------------------------------
def memset(tg, ptr: int, nbytes: int) -> None:
    """Clear ``nbytes`` at device address ``ptr`` (``cudaMemsetAsync`` on the target's stream)."""
    if not _wpc.runtime.core.wp_memset_device(tg.context, ptr, 0, nbytes, tg.stream):
        raise RuntimeError(f"ssgwarp: clearing a buffer on {tg.device} failed: {_wpc.runtime.get_error_string()}")


def copy_to_host(tg, host_ptr: int, device_ptr: int, nbytes: int) -> None:
    """Queue a copy of ``nbytes`` from the device to (pinned) host memory on the target's stream."""
    if not _wpc.runtime.core.wp_memcpy_d2h(tg.context, host_ptr, device_ptr, nbytes, tg.stream):
        raise RuntimeError(f"ssgwarp: reading a count back from {tg.device} failed: {_wpc.runtime.get_error_string()}")


def synchronize(tg) -> None:
    """Wait for the target's stream."""
    if not _wpc.runtime.core.wp_cuda_stream_synchronize(tg.stream):
        raise RuntimeError(f"ssgwarp: waiting for {tg.device} failed: {_wpc.runtime.get_error_string()}")


def sort_pairs_int64(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int, tg) -> None:
    """Warp's native stable radix sort of ``count`` int64 keys with 4-byte values over bits ``[0, end_bit)``, in
    place (``2 * count`` elements each: the upper half is scratch), on the target's stream."""
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


def sort_pairs_public(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int, tg, stream) -> None:
    """:func:`sort_pairs_int64` through Warp's public ``wp.utils.radix_sort_pairs`` (``stream``: Warp's wrapper of
    the target's stream, None on the CPU)."""
    ka = wp.from_torch(keys, dtype=wp.int64)
    va = wp.from_torch(values, dtype=wp.int32)
    with wp.ScopedDevice(tg.device), wp.ScopedStream(stream):
        wp.utils.radix_sort_pairs(ka, va, count, 0, end_bit)


# -- the Warp self-test -------------------------------------------------------------------------------------
_FAST: dict = {}   # device -> whether the Warp shortcuts passed their self-test there


def fast_path_works(tg, stream=None) -> bool:
    """Whether the Warp shortcuts may be used on the target's device: :data:`AVAILABLE` and, checked once per
    device (at its first launch), the probe kernel replayed forward and adjoint gives bit for bit what
    ``wp.launch`` gives, and so do the native sort (and on CUDA the clear and the read-back)."""
    if not AVAILABLE:
        return False
    ok = _FAST.get(tg.dkey)
    if ok is None:
        with _LOCK:
            ok = _FAST.get(tg.dkey)
            if ok is None:
                try:
                    why = _self_test(tg, stream)
                except Exception as e:  # (a replay that crashes Warp's side raises here, not in a render)
                    why = f"{type(e).__name__}: {e}"
                ok = _FAST[tg.dkey] = why is None
                if not ok:
                    _warn(f"Warp's fast launch path on {tg.device}", why)
    return ok


def _desc(t: torch.Tensor, inner: int = 1) -> tuple:
    return (t.data_ptr(), 0, t.numel() // inner, 0, 0, 0, t.element_size() * inner, 0, 0, 0, 1, 0)


def _self_test(tg, stream) -> str | None:
    """None where every shortcut agrees with the public call on ``tg``'s device, else what disagreed."""
    from ..kernels.probe import probe_kernel

    kernel = probe_kernel()
    dev = torch.device("cpu") if tg.cpu else torch.device("cuda", tg.dkey)
    n = 37
    g = torch.Generator().manual_seed(7)
    x = torch.randn(n, 3, generator=g).to(dev)
    w = torch.randn(n, generator=g).to(dev)
    params = (0.75, -3)
    w2 = (w.data_ptr(), 0, 2, n, 0, 0, 0, 4, 0, 0, 2, 0)   # [2, n] over n elements: first stride 0
    outs = {}
    for path in ("public", "replay"):
        y = torch.zeros(n, device=dev)
        adj_x, adj_w, adj_y = torch.zeros(n, 3, device=dev), torch.zeros(n, device=dev), torch.ones(n, device=dev)
        fwd = [*_desc(x, 3), *params, 5, *w2, *_desc(y)]
        adj = [*_desc(adj_x, 3), 0.0, 0, 0, *(adj_w.data_ptr(), 0, 2, n, 0, 0, 0, 4, 0, 0, 2, 0), *_desc(adj_y)]
        if path == "public":
            for a, adjoint in ((fwd, None), (fwd, adj)):
                wp.launch(kernel, dim=(n,), inputs=warp_args(kernel, a, tg.device),
                          adj_inputs=warp_args(kernel, adjoint, tg.device) if adjoint else [],
                          adjoint=adjoint is not None, device=tg.device, stream=stream, record_tape=False)
        else:
            for a, adjoint in ((fwd, None), (fwd, adj)):
                rep = Replay.record(kernel, tg, (n,), a, adjoint, None)
                if rep is None:
                    return "a recorded launch is not laid out as expected"
                rep.run(tg, (n,), n, a, adjoint)
        outs[path] = [y, adj_x, adj_w]
    if not tg.cpu:
        torch.cuda.synchronize(dev)
    want = (x[:, 0] + 2 * x[:, 1] - x[:, 2]) * 0.75 + (-3 + 5 * torch.arange(n, device=dev)).float() + w
    if not torch.allclose(outs["public"][0], want, rtol=1e-5, atol=1e-5):
        return "the probe kernel's public launch computed something else"
    if not all(torch.equal(a, b) for a, b in zip(outs["public"], outs["replay"])):
        return "a replayed launch gave other numbers than wp.launch"
    keys = torch.randint(0, 1 << 40, (2 * n,), generator=g, dtype=torch.int64).to(dev)
    vals = torch.arange(2 * n, dtype=torch.int32).to(dev)
    k2, v2 = keys.clone(), vals.clone()
    sort_pairs_public(keys, vals, n, 41, tg, stream)
    sort_pairs_int64(k2, v2, n, 41, tg)
    if not tg.cpu:
        torch.cuda.synchronize(dev)
    if not (torch.equal(keys[:n], k2[:n]) and torch.equal(vals[:n], v2[:n])):
        return "the native radix sort gave another order than wp.utils.radix_sort_pairs"
    if not tg.cpu and getattr(tg, "primary", False):
        t = torch.full((n,), 7, dtype=torch.int64, device=dev)
        memset(tg, t.data_ptr(), 8 * (n - 1))
        host = torch.empty(1, dtype=torch.int64, pin_memory=True)
        copy_to_host(tg, host.data_ptr(), t.data_ptr() + 8 * (n - 1), 8)
        synchronize(tg)
        if not (t[:-1].eq(0).all() and int(host[0]) == 7):
            return "the native clear or read-back gave other values than torch"
    return None


# -- torch: an autograd Function entered directly, torch's raw current stream -------------------------------
functorch_active = getattr(torch._C, "_are_functorch_transforms_active", lambda: True)
raw_stream = getattr(torch._C, "_cuda_getCurrentRawStream", None)   # (device index) -> stream handle, or None
# what Function.apply ends in (None where this torch has no such entry point)
_BASE_APPLY = getattr(getattr(torch._C, "_FunctionBase", None), "__dict__", {}).get("apply")
_APPLY_OK: list = []


class _Probe(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, k):
        ctx.save_for_backward(a, b)
        ctx.k = k
        return a * b + k, a - b

    @staticmethod
    def backward(ctx, g1, g2):
        a, b = ctx.saved_tensors
        return g1 * b + g2, g1 * a - g2, None


def _apply_self_test() -> str | None:
    # (its first use may come inside torch.no_grad() or inference mode: the check itself needs autograd)
    with torch.inference_mode(False), torch.enable_grad():
        return _apply_compare()


def _apply_compare() -> str | None:
    outs = []
    for entry in (_Probe.apply, _BASE_APPLY.__get__(None, _Probe)):
        a = torch.tensor([1.5, -2.0], requires_grad=True)
        b = torch.tensor([0.25, 3.0], requires_grad=True)
        y, z = entry(a, b, 2.0)
        (y.sum() * 3 + z.sum()).backward()
        outs.append([y.detach(), z.detach(), a.grad, b.grad])
    same = all(torch.equal(p, q) for p, q in zip(*outs))
    return None if same else "an autograd Function entered through torch._C._FunctionBase.apply differs"


def function_apply(fn):
    """``fn``'s autograd entry without ``Function.apply``'s Python (argument binding, functorch unwrapping), or
    None where it cannot be used (no such entry point, functorch transforms active, or its self-test failed:
    checked once, against ``Function.apply`` on a small Function, outputs and gradients)."""
    if _BASE_APPLY is None or functorch_active():
        return None
    if not _APPLY_OK:
        try:
            why = _apply_self_test()
        except Exception as e:
            why = f"{type(e).__name__}: {e}"
        _APPLY_OK.append(why is None)
        if why is not None:
            _warn("torch's direct autograd entry", why)
    return _BASE_APPLY.__get__(None, fn) if _APPLY_OK[0] else None


# -- torch: the fused Adam step without Adam.step's per-group Python -----------------------------------------
def fused_adam_groups(opt, adam_types: tuple) -> list | None:
    """``[(group, params, grads, exp_avgs, exp_avg_sqs, steps), ...]`` of the groups with gradients of a fused
    Adam (of one of ``adam_types``) whose parameters all have their state, or None where the step is left to
    ``opt.step()`` (hooks, another variant, a first step, a self-test that failed)."""
    from torch.optim import optimizer as torch_optimizer

    if (type(opt) not in adam_types or getattr(opt, "grad_scale", None) is not None
            or opt._optimizer_step_pre_hooks or opt._optimizer_step_post_hooks
            or torch_optimizer._global_optimizer_pre_hooks or torch_optimizer._global_optimizer_post_hooks):
        return None
    out = []
    for group in opt.param_groups:
        if (not group["fused"] or group["amsgrad"] or group["maximize"] or group["differentiable"]
                or group["decoupled_weight_decay"] or isinstance(group["lr"], torch.Tensor)
                or isinstance(group["betas"][0], torch.Tensor)):
            return None
        rows = [p for p in group["params"] if p.grad is not None]
        if not rows:
            continue
        states = [opt.state.get(p) for p in rows]
        if not all(states) or len({(p.device, p.dtype) for p in rows}) > 1:
            return None
        out.append((group, rows, [p.grad for p in rows], [s["exp_avg"] for s in states],
                    [s["exp_avg_sq"] for s in states], [s["step"] for s in states]))
    if out and not _adam_works(out[0][1][0].device.type, out[0][1][0].dtype):
        return None
    return out


def fused_adam_step(groups: list, found_inf) -> None:
    """Torch's fused Adam update of :func:`fused_adam_groups`' groups: the same ``torch._fused_adam_`` call per
    group, with the same arguments as ``Adam.step`` (so the same numbers to the bit), the step counts of all
    groups advanced (and, with ``found_inf`` set, taken back) in one call each."""
    steps = [s for g in groups for s in g[5]]
    torch._foreach_add_(steps, 1)
    for group, params, grads, exp_avgs, exp_avg_sqs, group_steps in groups:
        beta1, beta2 = group["betas"]
        torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], group_steps, amsgrad=False,
                           lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"],
                           eps=group["eps"], maximize=False, grad_scale=None, found_inf=found_inf)
    if found_inf is not None:
        torch._foreach_sub_(steps, [found_inf] * len(steps))


_ADAM_OK: dict = {}


def _adam_works(device_type: str, dtype: torch.dtype) -> bool:
    """Checked once per device type and dtype: two steps of :func:`fused_adam_step` equal ``Adam.step``'s."""
    key = (device_type, dtype)
    ok = _ADAM_OK.get(key)
    if ok is None:
        try:
            ok = _adam_compare(device_type, dtype)
            why = None if ok else "torch._fused_adam_ differs from Adam.step"
        except Exception as e:
            why = f"{type(e).__name__}: {e}"
        ok = _ADAM_OK[key] = why is None
        if not ok:
            _warn(f"the fused Adam step on {device_type}", why)
    return ok


def _adam_compare(device_type: str, dtype: torch.dtype) -> bool:
    with torch.inference_mode(False), torch.no_grad():
        dev = torch.device(device_type)
        g = torch.Generator().manual_seed(3)
        start = torch.randn(5, generator=g, dtype=dtype).to(dev)
        grads = [torch.randn(5, generator=g, dtype=dtype).to(dev) for _ in range(3)]
        a, b = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
        from ..core.optim import Adam   # (torch's Adam, whose step would import torch._dynamo)

        oa = Adam([a], lr=0.1, betas=(0.9, 0.99), eps=1e-15, weight_decay=0.01, fused=True)
        ob = Adam([b], lr=0.1, betas=(0.9, 0.99), eps=1e-15, weight_decay=0.01, fused=True)
        for i, gr in enumerate(grads):
            a.grad, b.grad = gr.clone(), gr.clone()
            oa.step()
            if i == 0:
                ob.step()   # (the state made)
            else:
                s = ob.state[b]
                fused_adam_step([(ob.param_groups[0], [b], [b.grad], [s["exp_avg"]], [s["exp_avg_sq"]],
                                  [s["step"]])], None)
        return torch.equal(a, b) and all(torch.equal(oa.state[a][k], ob.state[b][k])
                                         for k in ("exp_avg", "exp_avg_sq", "step"))
