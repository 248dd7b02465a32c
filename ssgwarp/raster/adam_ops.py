"""Adam as one Warp launch over every parameter group (``kernels/adam.py``): :class:`WarpAdam`.

torch's fused Adam updates one parameter group per kernel (the reconstruction keeps one group per
tensor for its own learning rate: six or seven launches a step, plus the step counts' own ops).
:class:`WarpAdam` updates all of them in one launch: a table of the groups' addresses, element ranges
and step constants (bias corrections worked out on the host from each group's step count) is written to
pinned memory, copied to the device behind the step's other work (CUDA) and read by the kernel; on the
CPU the kernel reads it in place.

It is ``torch.optim.Adam`` in everything but ``step``: the same parameter groups, the same per-parameter
state (``step``, ``exp_avg``, ``exp_avg_sq``: the step count a float32 CPU tensor, as torch's default
Adam keeps it), so densification's row surgery, checkpoints and ``load_state_dict`` from and into
torch's Adam work unchanged. Where it cannot run (a parameter that is not a contiguous float32 tensor,
parameters on several devices, AMSGrad, ``maximize``, decoupled weight decay, a tensor learning rate)
``step`` is torch's. A step whose ``found_inf`` flag is set (the trainer's deferred NaN check) leaves
parameters and moments unchanged on the device; its step count on the host advances (the run stops at
that flag anyway: ``ssgwarp.reconstruction.step.LossWatch``).
"""
from __future__ import annotations

import math

import torch

from ..core.optim import Adam
from ..kernels.adam import CONSTANTS, COUNT, ROW, adam_kernel
from . import launch as L

SLOTS = 4   # pinned host tables in turn: one is written while the copies of the last steps may be pending
CPU_CHUNK = 4096   # elements per thread on the CPU (one on CUDA)


class WarpAdam(Adam):
    """``torch.optim.Adam`` stepped by one Warp kernel over all its parameters (see the module's text)."""

    skips_found_inf = True   # a set ``found_inf`` skips the update on the device (LossWatch defers its check)

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-8, weight_decay: float = 0.0):
        super().__init__(params, lr=lr, betas=betas, eps=eps, weight_decay=weight_decay, foreach=False, fused=False)
        self._host: list = []      # [(pinned or plain int64 table, its float32 view as numpy, CUDA event)]
        self._turn = 0
        self._device_table = None

    def load_state_dict(self, state_dict: dict) -> None:
        """torch's, then the groups' flags and the step counts as :class:`WarpAdam` keeps them (a state dict of
        torch's fused Adam holds device step counts and ``fused=True``)."""
        super().load_state_dict(state_dict)
        for group in self.param_groups:
            group["fused"], group["foreach"], group["capturable"] = False, False, False
        for st in self.state.values():
            if torch.is_tensor(st.get("step")):
                st["step"] = torch.tensor(float(st["step"]), dtype=torch.float32)

    def _rows(self) -> list | None:
        """``[(group, param), ...]`` of the parameters with gradients, or None where the kernel cannot step them."""
        out, devices = [], set()
        for group in self.param_groups:
            if (group["amsgrad"] or group["maximize"] or group["differentiable"] or group.get("decoupled_weight_decay")
                    or torch.is_tensor(group["lr"]) or torch.is_tensor(group["betas"][0])):
                return None
            for p in group["params"]:
                g = p.grad
                if g is None:
                    continue
                if (p.dtype != torch.float32 or g.dtype != torch.float32 or g.is_sparse or not p.is_contiguous()
                        or not g.is_contiguous() or p.device.type not in ("cpu", "cuda")):
                    return None
                devices.add(p.device)
                out.append((group, p))
        return None if len(devices) > 1 else out

    def _table(self, n: int, device: torch.device):
        """The host table for the next step (``n`` rows) and, on CUDA, the device table it is copied into."""
        cuda = device.type == "cuda"
        if not self._host or self._host[0][0].shape[0] < n or self._host[0][0].is_pinned() != cuda:
            rows = max(n, 8)
            self._host = []
            for _ in range(SLOTS if cuda else 1):
                t = torch.zeros(rows, ROW, dtype=torch.int64, pin_memory=cuda)
                self._host.append([t, t.view(torch.float32).numpy(), None])
            self._device_table = torch.zeros(rows, ROW, dtype=torch.int64, device=device) if cuda else None
        slot = self._host[self._turn % len(self._host)]
        self._turn += 1
        if slot[2] is not None:
            slot[2].synchronize()   # (the copy from this slot several steps ago: long done)
        return slot

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        rows = self._rows()
        if rows is None:
            return super().step()
        if not rows:
            return loss
        total = sum(p.numel() for _, p in rows)
        if total > L.INT32_MAX:
            return super().step()
        device = rows[0][1].device
        chunk = 1 if device.type == "cuda" else CPU_CHUNK
        slot = self._table(len(rows), device)
        ints, floats = slot[0].numpy(), slot[1]
        end = 0
        for k, (group, p) in enumerate(rows):
            st = self.state[p]
            if not st:
                st["step"] = torch.tensor(0.0, dtype=torch.float32)
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            count = st["step"].numpy()   # (a float32 CPU scalar: advanced in place)
            count += 1
            t = float(count)
            beta1, beta2 = group["betas"]
            end += -(-p.numel() // chunk)
            ints[k, :COUNT + 1] = (p.data_ptr(), p.grad.data_ptr(), st["exp_avg"].data_ptr(),
                                   st["exp_avg_sq"].data_ptr(), end, p.numel())
            floats[k, CONSTANTS:CONSTANTS + 7] = (group["lr"] / (1.0 - beta1 ** t), 1.0 / math.sqrt(1.0 - beta2 ** t),
                                                  1.0 - beta1, beta2, 1.0 - beta2, group["eps"], group["weight_decay"])
        table = slot[0]
        if device.type == "cuda":
            self._device_table.copy_(table, non_blocking=True)
            slot[2] = torch.cuda.Event()
            slot[2].record()
            table = self._device_table
        skip = getattr(self, "found_inf", None)
        tg = L.target(rows[0][1])
        L.launch(adam_kernel(), end, [*L.arr(table), *L.arr(table.view(torch.float32)), len(rows), chunk,
                                      *(L.arr(skip.reshape(1)) if skip is not None else L.NULL)], tg)
        return loss


def warp_adam(params, **kwargs) -> Adam:
    """:class:`WarpAdam` when every parameter is float32 on one CPU or CUDA device, else
    ``ssgwarp.core.optim.adam`` (torch's fused Adam)."""
    from ..core.optim import adam

    groups = list(params)
    tensors = [p for g in groups for p in (g["params"] if isinstance(g, dict) else [g])]
    if tensors and len({p.device for p in tensors}) == 1 and all(
            p.dtype == torch.float32 and p.device.type in ("cpu", "cuda") for p in tensors):
        return WarpAdam(groups, **{k: v for k, v in kwargs.items() if k not in ("fused", "foreach")})
    return adam(groups, **kwargs)
