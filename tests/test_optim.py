"""The PPO recipe's large-batch options: optimiser and learning-rate schedule (``torchsim.algos.optim``), and
bfloat16 matrix products (``algos.networks.Bfloat16Matmuls``)."""

import math

import pytest
import torch
from omegaconf import OmegaConf

from torchsim.algos.networks import Bfloat16Matmuls, mlp
from torchsim.algos.optim import make_optimizer, make_schedule


def _algo(**keys):
    return OmegaConf.create({"lr": 1e-3, "optimizer": "adam", "lr_reference_batch": None, "lr_warmup_steps": 0,
                             "anneal_lr": False, "lr_decay": "linear", **keys})


def _rates(optim, schedule, updates):
    rates = []
    for _ in range(updates):
        rates.append(optim.param_groups[0]["lr"])
        optim.step()
        schedule.step()
    return rates


def test_linear_anneal_is_torchs_linear_lr():
    frames, budget = 100, 1000
    ours = make_optimizer([torch.nn.Parameter(torch.zeros(1))], _algo(anneal_lr=True), frames)
    theirs = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1e-3)
    ours_rates = _rates(ours, make_schedule(ours, _algo(anneal_lr=True), budget, frames), 12)
    theirs_rates = _rates(theirs, torch.optim.lr_scheduler.LinearLR(theirs, 1.0, 0.0, total_iters=10), 12)
    assert ours_rates == pytest.approx(theirs_rates, abs=1e-12)
    assert ours_rates[10] == ours_rates[11] == 0.0


def test_warmup_then_cosine_and_square_root_batch_scaling():
    a = _algo(anneal_lr=True, lr_decay="cosine", lr_warmup_steps=400, lr_reference_batch=25)
    frames, budget = 100, 1400  # 4 warm-up updates, then 10 of cosine
    optim = make_optimizer([torch.nn.Parameter(torch.zeros(1))], a, frames)
    peak = 1e-3 * math.sqrt(frames / 25)
    rates = _rates(optim, make_schedule(optim, a, budget, frames), 15)
    assert rates[:4] == pytest.approx([peak / 4, peak / 2, 3 * peak / 4, peak])
    assert rates[4 + 5] == pytest.approx(peak / 2)  # half way down the cosine
    assert rates[14] == pytest.approx(0.0, abs=1e-15)
    assert make_schedule(optim, _algo(), None, frames) is None  # constant rate


def test_lamb_steps_each_tensor_in_proportion_to_its_norm():
    """LAMB's defining property (the layer-wise trust ratio): each tensor moves by the same fraction of its own norm,
    whatever its gradient's scale (here 1e6 apart), where Adam would move every entry by about the same amount."""
    torch.manual_seed(0)
    big, small = torch.nn.Parameter(torch.randn(50) * 0.7), torch.nn.Parameter(torch.randn(50) * 0.07)  # |w| ~5, 0.5
    optim = make_optimizer([big, small], _algo(optimizer="lamb", lr=1e-3), 100)
    before = [big.detach().clone(), small.detach().clone()]
    (big.square().sum() * 1e3 + small.square().sum() * 1e-3).backward()
    optim.step()
    fractions = [float((p.detach() - p0).norm() / p0.norm()) for p, p0 in zip((big, small), before)]
    assert fractions[0] == pytest.approx(fractions[1], rel=1e-3)
    assert 1e-4 < fractions[0] < 1e-1
    assert big.detach().norm() < before[0].norm() and small.detach().norm() < before[1].norm()  # downhill


def test_bad_options_name_the_key():
    with pytest.raises(ValueError, match="algo.optimizer"):
        make_optimizer([torch.nn.Parameter(torch.zeros(1))], _algo(optimizer="sgd"), 1)
    optim = make_optimizer([torch.nn.Parameter(torch.zeros(1))], _algo(), 1)
    with pytest.raises(ValueError, match="algo.lr_decay"):
        make_schedule(optim, _algo(lr_decay="step"), 10, 1)
    with pytest.raises(ValueError, match="budget.env_steps"):
        make_schedule(optim, _algo(anneal_lr=True), None, 1)


def test_bf16_network_matches_float32_to_bfloat16_precision():
    """The same weights, float32 and bfloat16 matrix products: outputs and gradients in float32, apart by about
    bfloat16's relative precision (2^-8) times the sizes involved, not more."""
    torch.manual_seed(0)
    cfg = OmegaConf.create({"hidden": [256, 256], "activation": "silu", "bf16": True})
    net = mlp(27, 1, cfg, "cpu")
    assert isinstance(net, Bfloat16Matmuls)
    x = torch.randn(640, 27)
    low, full = net(x), net.net(x)
    assert low.dtype == torch.float32
    scale = full.abs().max()
    assert 0 < (low - full).abs().max() < 0.05 * scale
    low.sum().backward()
    grads = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    full.sum().backward()
    for g, g_full in zip(grads, (p.grad for p in net.parameters())):
        assert g.dtype == torch.float32
        assert (g - g_full).norm() < 0.05 * g_full.norm()
