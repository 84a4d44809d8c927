"""Policy and value networks for the navigation envs (``torchsim.envs.nav``, PointNav): a compact residual CNN over
the depth image, an embedding of the point goal, and an MLP head, as TorchRL modules.

The encoder follows the published SE-ResNet9 of DD-PPO in spirit, sized for CPU training: a strided stem, then per
stage a strided 3x3 convolution and ``blocks`` residual blocks (two 3x3 convolutions, a squeeze-and-excitation
gate, the skip connection), no normalisation layers, ReLU throughout. Depth arrives standardised per pixel by the
recipe's running normaliser (``algos/env_factory.py``, ``make_env``). The goal ``(distance, angle)`` enters as
``(log(1 + distance), cos angle, sin angle)`` through a linear layer and ReLU. The head is the recipe's ``mlp``
(passed in as ``make_head``: this module does not import ``networks``, which imports it).

With ``cfg_net.lstm`` > 0 (the policy's config; 0 or absent: none) the networks are recurrent, as DD-PPO's: encoder
and goal embedding feed a TorchRL ``LSTMModule`` of that many units, the trunk that the policy head and the value
head share (:func:`make_value` builds the value on the policy's trunk). Sharing it keeps one recurrent state per
env, which the collector carries from step to step as the actor runs (a critic with its own LSTM would need its
states carried too, though the collector never runs it). The env holds the states (:func:`recurrent_transforms`,
added by ``algos/nav_task.py``, ``make_base``) and zeroes them at every episode start; PPO trains on whole per-env
sequences in recurrent mode (``algos/ppo.py``).
"""

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import OneHot
from torchrl.envs import InitTracker, Transform
from torchrl.modules import LSTMModule, OneHotCategorical, ProbabilisticActor, ValueOperator

from torchsim.envs.nav.pointnav import STOP

#: The encoder when ``cfg_net.encoder`` leaves a key out: ``stem`` output channels of a convolution with stride
#: ``stem_stride`` and kernel twice that;
#: per stage, output ``channels`` (3x3 convolution, stride 2) and ``blocks`` residual blocks; a linear layer to
#: ``features``; the goal embedding's width ``goal_features``.
ENCODER_DEFAULTS = {"stem": 16, "stem_stride": 4, "channels": [16, 32], "blocks": 1, "features": 128,
                    "goal_features": 32}


#: How far below the other actions' logits the untrained policy's STOP logit starts (:func:`make_actor`).
STOP_LOGIT_INIT = 3.0


def is_nav_env(env) -> bool:
    """Whether ``env`` (a TorchRL env, transformed or not) is a navigation task: it emits ``pointgoal``."""
    return "pointgoal" in env.observation_spec.keys()


class SqueezeExcite(nn.Module):
    """Channel gate: global average pool, bottleneck MLP (``reduction``), sigmoid; scales each channel."""

    def __init__(self, channels: int, device, reduction: int = 4):
        super().__init__()
        self.gate = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten(),
                                  nn.Linear(channels, max(1, channels // reduction), device=device), nn.ReLU(),
                                  nn.Linear(max(1, channels // reduction), channels, device=device), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gate(x)[:, :, None, None]


class ResidualBlock(nn.Module):
    """``relu(x + se(conv(relu(conv(x)))))`` with 3x3 convolutions keeping the channels and the resolution."""

    def __init__(self, channels: int, device):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1, device=device), nn.ReLU(),
                                  nn.Conv2d(channels, channels, 3, padding=1, device=device),
                                  SqueezeExcite(channels, device))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x + self.body(x))


class DepthEncoder(nn.Module):
    """Depth ``(N, 1, H, W)`` -> features ``(N, features)`` (:data:`ENCODER_DEFAULTS`), ``chunk`` images at a time:
    a whole training batch at once (GAE's values) leaves the caches and ran ~1.8x slower per image on this CPU
    (67 against 37 us for 4,096 images in one call against 1,024 per call)."""

    chunk = 1024

    def __init__(self, image_shape, enc: dict, device):
        super().__init__()
        if not enc["channels"] or int(enc["blocks"]) < 0:
            raise ValueError(f"the encoder needs at least one stage and blocks >= 0, got {enc}")
        c, stride = int(enc["stem"]), int(enc["stem_stride"])
        layers = [nn.Conv2d(image_shape[0], c, 2 * stride, stride, padding=stride // 2, device=device), nn.ReLU()]
        for out in enc["channels"]:
            layers += [nn.Conv2d(c, out, 3, stride=2, padding=1, device=device), nn.ReLU()]
            layers += [ResidualBlock(out, device) for _ in range(int(enc["blocks"]))]
            c = out
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            flat = self.conv(torch.zeros(1, *image_shape, device=device)).shape[-1]
        self.project = nn.Sequential(nn.Linear(flat, int(enc["features"]), device=device), nn.ReLU())

    def forward(self, depth: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.project(self.conv(part)) for part in depth.split(self.chunk)])


class NavNet(nn.Module):
    """``(depth (..., 1, H, W), pointgoal (..., 2))`` -> ``head(concat(depth features, goal embedding))``, or with
    ``out_features`` None (a recurrent trunk's input) the concatenation itself, ``embedding_size`` wide; with
    ``bf16``, the encoder runs under ``torch.autocast`` to bfloat16 (its output back in float32)."""

    def __init__(self, depth_spec, cfg_net: DictConfig, out_features: int | None, make_head, device):
        super().__init__()
        enc = {**ENCODER_DEFAULTS, **cfg_net.get("encoder", {})}
        unknown = set(enc) - set(ENCODER_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown encoder keys {sorted(unknown)}; known: {sorted(ENCODER_DEFAULTS)}")
        self.encoder = DepthEncoder(tuple(depth_spec.shape[-3:]), enc, device)
        self.goal = nn.Sequential(nn.Linear(3, int(enc["goal_features"]), device=device), nn.ReLU())
        self.embedding_size = int(enc["features"]) + int(enc["goal_features"])
        self.head = nn.Identity() if out_features is None else make_head(self.embedding_size, out_features, cfg_net,
                                                                         device)
        self.bf16 = bool(cfg_net.get("bf16", False))

    def forward(self, depth: torch.Tensor, pointgoal: torch.Tensor) -> torch.Tensor:
        lead = depth.shape[:-3]
        with torch.autocast(depth.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            z = self.encoder(depth.reshape(-1, *depth.shape[-3:])).float().reshape(*lead, -1)
        distance, angle = pointgoal.unbind(-1)
        goal = self.goal(torch.stack([torch.log1p(distance), torch.cos(angle), torch.sin(angle)], -1))
        return self.head(torch.cat([z, goal], -1))


def lstm_size(cfg_net: DictConfig) -> int:
    """The LSTM's units of a policy config (``cfg_net.lstm``): 0 for a feed-forward policy."""
    return int(cfg_net.get("lstm", 0) or 0)


def make_lstm(input_size: int, hidden_size: int, device) -> LSTMModule:
    """An LSTM from ``nav_embedding`` to ``nav_memory``; its states are TorchRL's default keys, read at the root
    (``recurrent_state_h``, ``recurrent_state_c``) and written under ``next``, with ``is_init`` zeroing them."""
    return LSTMModule(input_size=input_size, hidden_size=hidden_size, in_key="nav_embedding", out_key="nav_memory",
                      device=device)


def recurrent_transforms(cfg_net: DictConfig) -> list[Transform]:
    """The env transforms a recurrent policy (``cfg_net.lstm`` > 0) needs, else none: ``InitTracker`` (``is_init``,
    True at every episode's first step, partial resets included) and the primer of the LSTM's states (zero at reset;
    it depends only on their keys and sizes, so a one-input LSTM's primer serves)."""
    hidden = lstm_size(cfg_net)
    return [InitTracker(), make_lstm(1, hidden, "cpu").make_tensordict_primer()] if hidden else []


def is_recurrent(actor) -> bool:
    """Whether ``actor`` (or any module) holds an LSTM, so reads and writes recurrent states."""
    return any(isinstance(m, LSTMModule) for m in actor.modules())


def make_actor(env, cfg_net: DictConfig, device, make_head) -> ProbabilisticActor:
    """Categorical policy over the env's discrete actions (``OneHotCategorical`` for a one-hot action spec), from
    logits of a :class:`NavNet`; its deterministic action is the most probable one. The STOP logit (action 0)
    starts ``STOP_LOGIT_INIT`` below the others, so the untrained policy STOPs in ~2% of its steps, not 25%: its
    episodes run long enough to meet the goal-distance reward (stopping at once scores 0, wandering a little less),
    and the env spends less time on resets (a wavefront each). With ``cfg_net.lstm``, the logits are the head's on
    the output of the recurrent trunk (encoders, then the LSTM)."""
    spec = env.action_spec_unbatched
    one_hot = isinstance(spec, OneHot)
    n = spec.shape[-1] if one_hot else int(spec.n)
    hidden = lstm_size(cfg_net)
    if hidden:
        net = NavNet(env.observation_spec["depth"], cfg_net, None, make_head, device)
        trunk = TensorDictSequential(TensorDictModule(net, in_keys=["depth", "pointgoal"], out_keys=["nav_embedding"]),
                                     make_lstm(net.embedding_size, hidden, device))
        head = make_head(hidden, n, cfg_net, device)
        module = TensorDictSequential(trunk, TensorDictModule(head, in_keys=["nav_memory"], out_keys=["logits"]))
    else:
        head = NavNet(env.observation_spec["depth"], cfg_net, n, make_head, device)
        module = TensorDictModule(head, in_keys=["depth", "pointgoal"], out_keys=["logits"])
    with torch.no_grad():
        [m for m in head.modules() if isinstance(m, nn.Linear)][-1].bias[STOP] -= STOP_LOGIT_INIT
    dist = OneHotCategorical if one_hot else torch.distributions.Categorical
    return ProbabilisticActor(module, in_keys=["logits"], spec=spec, distribution_class=dist, return_log_prob=True)


def make_value(env, cfg_net: DictConfig, device, make_head, actor=None) -> TensorDictModule:
    """V(depth, pointgoal): a :class:`NavNet` with one output; for a recurrent ``actor``, ``cfg_net``'s head on the
    actor's trunk (encoders and LSTM, shared: their gradients come from both losses)."""
    if actor is not None and is_recurrent(actor):
        trunk = actor.module[0][0]
        head = make_head(trunk[-1].lstm.hidden_size, 1, cfg_net, device)
        return TensorDictSequential(trunk, ValueOperator(head, in_keys=["nav_memory"]))
    net = NavNet(env.observation_spec["depth"], cfg_net, 1, make_head, device)
    return ValueOperator(net, in_keys=["depth", "pointgoal"])
