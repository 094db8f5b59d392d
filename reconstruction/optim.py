"""Adam with PyTorch's one-cycle schedule, without ``torch.optim``.

Why not ``torch.optim.Adam``: in torch 2.x every ``torch.optim.Optimizer`` imports ``torch._dynamo`` (the
compiler) when it is created (``add_param_group`` is wrapped in ``torch._disable_dynamo``) and when it steps
(``_use_grad_for_differentiable`` imports it on every call). That import costs 3-4 s on a quiet 2-core machine and
4-14 s under load, longer than a short window's whole fit. Neither ``foreach=False`` nor ``fused=False`` avoids it.

:class:`Adam` performs exactly the update of ``torch.optim.Adam``'s default CPU path (``_single_tensor_adam``:
no weight decay, no amsgrad, not maximising; the same tensor operations in the same order, the step count kept
as a float), and :func:`one_cycle` gives exactly the learning rates and beta1 of
``torch.optim.lr_scheduler.OneCycleLR`` (cosine annealing, two phases, ``cycle_momentum``), so a fit gives the
same numbers as with torch's classes (``tests/reconstruction/test_optim.py`` checks both against torch to the
last bit).

    opt = Adam([{"params": [a, b], "lr": 0.05}, {"params": [c], "lr": 0.01}])
    sched = OneCycle(opt, total_steps=200, pct_start=0.15)
    for i in range(200):
        opt.zero_grad()
        energy().backward()
        opt.step()
        sched.step()
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

__all__ = ["Adam", "OneCycle", "one_cycle"]


class Adam:
    """``torch.optim.Adam(groups, lr, betas, eps)`` (weight decay 0, no amsgrad), without importing
    ``torch._dynamo``. ``params``: tensors, or groups ``{"params": [...], "lr": ...}`` as torch takes them;
    ``param_groups`` holds each group's ``lr`` and ``betas`` (what a schedule changes)."""

    def __init__(self, params: Iterable, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        params = list(params)
        if not params:
            raise ValueError("Adam got an empty parameter list")
        groups = params if isinstance(params[0], dict) else [{"params": params}]
        self.param_groups: list[dict] = []
        for g in groups:
            g = dict(g)
            g["params"] = list(g["params"])
            g.setdefault("lr", lr)
            g.setdefault("betas", betas)
            g.setdefault("eps", eps)
            for p in g["params"]:
                if not isinstance(p, torch.Tensor) or not p.requires_grad:
                    raise ValueError("Adam optimises tensors that require grad")
            self.param_groups.append(g)
        self.state: dict[torch.Tensor, dict] = {}

    def zero_grad(self) -> None:
        """Drop the gradients (``set_to_none=True``, torch's default)."""
        for g in self.param_groups:
            for p in g["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        for g in self.param_groups:
            lr, (beta1, beta2), eps = g["lr"], g["betas"], g["eps"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                grad = p.grad
                st = self.state.get(p)
                if st is None:
                    st = self.state[p] = {"step": 0.0, "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                          "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
                # torch keeps the step in a float32 tensor and reads it back with .item(): exact for any count used here
                st["step"] += 1.0
                step = st["step"]
                exp_avg, exp_avg_sq = st["exp_avg"], st["exp_avg_sq"]
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                bias_correction1 = 1 - beta1**step
                bias_correction2 = 1 - beta2**step
                step_size = lr / bias_correction1
                bias_correction2_sqrt = bias_correction2**0.5
                denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(eps)
                p.addcdiv_(exp_avg, denom, value=-step_size)


def one_cycle(step: int, total_steps: int, max_lr: float, pct_start: float = 0.3, div_factor: float = 25.0,
              final_div_factor: float = 1e4, base_momentum: float = 0.85, max_momentum: float = 0.95) -> tuple[float, float]:
    """(lr, beta1) of ``torch.optim.lr_scheduler.OneCycleLR`` (``anneal_strategy="cos"``, two phases,
    ``cycle_momentum=True``) at scheduler step ``step`` (0 = as created)."""
    if step > total_steps:
        raise ValueError(f"step {step} beyond the schedule's {total_steps} steps")
    initial = max_lr / div_factor
    phases = ((float(pct_start * total_steps) - 1, initial, max_lr, max_momentum, base_momentum),
              (total_steps - 1, max_lr, initial / final_div_factor, base_momentum, max_momentum))
    start = 0.0
    for i, (end, lr0, lr1, m0, m1) in enumerate(phases):
        if step <= end or i == len(phases) - 1:
            pct = (step - start) / (end - start)
            return _cos(lr0, lr1, pct), _cos(m0, m1, pct)
        start = end
    raise AssertionError("unreachable")  # pragma: no cover


def _cos(start: float, end: float, pct: float) -> float:
    cos_out = math.cos(math.pi * pct) + 1
    return end + (start - end) / 2.0 * cos_out


class OneCycle:
    """``torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=[each group's lr], total_steps, pct_start)`` for
    :class:`Adam`: sets each group's ``lr`` and beta1 now (step 0) and at every :meth:`step`."""

    def __init__(self, opt: Adam, total_steps: int, pct_start: float = 0.3, max_lr: list[float] | None = None) -> None:
        if not 0 <= pct_start <= 1:
            raise ValueError(f"pct_start must be in [0, 1], got {pct_start}")
        if total_steps <= 0:
            raise ValueError(f"total_steps must be positive, got {total_steps}")
        self.opt, self.total_steps, self.pct_start = opt, int(total_steps), float(pct_start)
        self.max_lr = [g["lr"] for g in opt.param_groups] if max_lr is None else list(max_lr)
        self.last_step = -1
        self.step()

    def step(self) -> None:
        self.last_step += 1
        for g, m in zip(self.opt.param_groups, self.max_lr, strict=True):
            lr, beta1 = one_cycle(self.last_step, self.total_steps, m, self.pct_start)
            g["lr"], g["betas"] = lr, (beta1, g["betas"][1])
