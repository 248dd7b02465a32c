"""The scene's per-Gaussian tensors as a strategy edits them: :class:`GaussianParams` (parameters, their Adam
state and a strategy's per-Gaussian statistics, changed row-wise together: append, keep, overwrite, reset)."""
from __future__ import annotations

from typing import Callable, Optional

import torch


class GaussianParams:
    """The per-Gaussian tensors, their Adam optimizer and per-Gaussian statistics, edited row-wise.

    ``params`` maps names to ``[N, ...]`` parameters, each alone in an optimizer
    parameter group whose ``"name"`` is that name; ``stats`` maps names to ``[N, ...]``
    buffers a strategy keeps (not optimised). Every method below changes the rows of
    all of them at once, so they always agree on N and on which row is which Gaussian;
    Adam moments of rows that are new or were rewritten are zero.
    """

    def __init__(self, params: dict[str, torch.nn.Parameter], opt: torch.optim.Optimizer,
                 stats: Optional[dict[str, torch.Tensor]] = None):
        self.params = params
        self.opt = opt
        self.stats: dict[str, torch.Tensor] = dict(stats or {})

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def groups(self) -> dict[str, dict]:
        """Optimizer parameter groups by name (looked up each time: loading a state dict replaces them)."""
        return {g["name"]: g for g in self.opt.param_groups if "name" in g}

    def _moments(self, p: torch.Tensor) -> dict:
        """The optimizer state of ``p`` restricted to its per-row tensors (Adam's moments, not its step)."""
        st = self.opt.state.get(p, {})
        return {k: v for k, v in st.items() if torch.is_tensor(v) and v.shape == p.shape}

    def set(self, name: str, value: torch.Tensor,
            state_fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
        """Replace parameter ``name`` by ``value``; its per-row optimizer state goes through ``state_fn``."""
        group = self.groups[name]
        old = group["params"][0]
        st = self.opt.state.pop(old, None)
        p = torch.nn.Parameter(value.detach().contiguous())
        group["params"][0] = p
        if st is not None:
            self.opt.state[p] = {k: (state_fn(v) if torch.is_tensor(v) and v.shape == old.shape else v)
                                 for k, v in st.items()}
        self.params[name] = p

    @torch.no_grad()
    def keep(self, mask: torch.Tensor) -> None:
        """Keep the rows where ``mask`` (bool ``[N]``) is true, in order."""
        for name in list(self.params):
            self.set(name, self.params[name].data[mask], lambda s: s[mask])
        self.stats = {k: v[mask] for k, v in self.stats.items()}

    @torch.no_grad()
    def append(self, rows: dict[str, torch.Tensor]) -> None:
        """Append rows (one ``[K, ...]`` tensor per parameter; statistics and Adam moments start at 0)."""
        missing = set(self.params) - set(rows)
        if missing:
            raise ValueError(f"GaussianParams.append: no rows for {sorted(missing)}")
        k = int(next(iter(rows.values())).shape[0])

        def grow(s: torch.Tensor) -> torch.Tensor:
            return torch.cat([s, s.new_zeros((k,) + tuple(s.shape[1:]))])
        for name in list(self.params):
            self.set(name, torch.cat([self.params[name].data, rows[name].to(self.params[name].dtype)]), grow)
        self.stats = {n: grow(v) for n, v in self.stats.items()}

    @torch.no_grad()
    def assign(self, idx: torch.Tensor, rows: dict[str, torch.Tensor]) -> None:
        """Overwrite rows ``idx`` (long ``[K]``) of the parameters named in ``rows`` (``[K, ...]`` each).

        The Gaussians at ``idx`` are new ones: the Adam moments and statistics of those rows are
        zeroed for every tensor, named or not. In place (the parameters stay the same objects).
        """
        for name, value in rows.items():
            self.params[name].data[idx] = value.to(self.params[name].dtype)
        for p in self.params.values():
            for v in self._moments(p).values():
                v[idx] = 0
        for v in self.stats.values():
            v[idx] = 0

    @torch.no_grad()
    def zero_moments(self, name: str) -> None:
        """Zero the Adam moments of every row of parameter ``name``."""
        for v in self._moments(self.params[name]).values():
            v.zero_()
