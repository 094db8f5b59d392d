"""reconstruction.optim: the same numbers as torch.optim.Adam + OneCycleLR, without importing torch._dynamo."""

import subprocess
import sys

import pytest
import torch

from reconstruction.optim import Adam, OneCycle, one_cycle


def _problem(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(40, 6, generator=g)
    y = torch.randn(40, generator=g)
    x0 = [torch.randn(6, generator=g), torch.randn(3, 2, generator=g), torch.randn(4, generator=g)]
    unused = torch.randn(2, generator=g)  # never gets a gradient: both optimisers must leave it alone

    def energy(a, b, c, u):
        r = A @ a + (b**2).sum() * torch.sin(y) - c.sum() * y
        return (r**2).mean() + torch.tanh(b).abs().sum() + 0.1 * (c**4).sum()

    return energy, x0, unused


def _run(make_opt, make_sched, iters=60):
    energy, x0, unused = _problem()
    a, b, c = (x.clone().requires_grad_() for x in x0)
    u = unused.clone().requires_grad_()
    groups = [{"params": [a, b], "lr": 0.05}, {"params": [c], "lr": 0.02}, {"params": [u], "lr": 0.1}]
    opt = make_opt(groups)
    sched = make_sched(opt, [g["lr"] for g in groups], iters)
    lrs = []
    for _ in range(iters):
        opt.zero_grad()
        energy(a, b, c, u).backward()
        opt.step()
        sched.step()
        lrs.append([(g["lr"], g["betas"][0]) for g in opt.param_groups])
    return [t.detach() for t in (a, b, c, u)], lrs


def test_adam_one_cycle_equal_to_torch_bit_for_bit():
    ours, lr_ours = _run(Adam, lambda o, m, n: OneCycle(o, n, pct_start=0.15, max_lr=m))
    theirs, lr_theirs = _run(torch.optim.Adam, lambda o, m, n: torch.optim.lr_scheduler.OneCycleLR(
        o, max_lr=m, total_steps=n, pct_start=0.15))
    assert lr_ours == lr_theirs
    for x, y in zip(ours, theirs):
        assert torch.equal(x, y), (x - y).abs().max()
    assert not torch.equal(ours[0], _problem()[1][0])  # it moved


def test_one_cycle_ends_and_refuses_steps_beyond():
    lr0, b0 = one_cycle(0, 100, 1.0, 0.15)
    assert lr0 == pytest.approx(1.0 / 25) and b0 == pytest.approx(0.95)
    assert one_cycle(14, 100, 1.0, 0.15)[0] == pytest.approx(1.0)
    assert one_cycle(99, 100, 1.0, 0.15)[0] == pytest.approx(1.0 / 25 / 1e4)
    with pytest.raises(ValueError, match="beyond"):
        one_cycle(101, 100, 1.0, 0.15)


def test_adam_refuses_tensors_without_grad():
    with pytest.raises(ValueError, match="require grad"):
        Adam([torch.zeros(3)])


def test_no_dynamo_import():
    """A fit's optimiser loop leaves torch._dynamo unimported (its import costs seconds)."""
    code = (
        "import sys, torch\n"
        "from reconstruction.optim import Adam, OneCycle\n"
        "x = torch.zeros(3, requires_grad=True)\n"
        "opt = Adam([{'params': [x], 'lr': 0.1}]); s = OneCycle(opt, 5)\n"
        "for _ in range(5):\n"
        "    opt.zero_grad(); ((x - 1) ** 2).sum().backward(); opt.step(); s.step()\n"
        "assert 'torch._dynamo' not in sys.modules, 'torch._dynamo was imported'\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
