"""The recipes' networks: MLPs (optionally with bfloat16 matrix products), the pixel CNN (:class:`PixelNet`) and its
auxiliary state read-out (:class:`StateProbe`), and the actor and critic builders for every kind of env (state,
pixels, navigation: ``torchsim.algos.nav_policy``)."""

import torch
from omegaconf import DictConfig
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.modules import MLP, IndependentNormal, NormalParamExtractor, ProbabilisticActor, TanhNormal, ValueOperator

from torchsim.algos import nav_policy

ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "tanh": nn.Tanh, "elu": nn.ELU}


def mlp(in_features: int, out_features: int, cfg_net: DictConfig, device) -> nn.Module:
    """The MLP of ``cfg_net`` (``hidden`` sizes, ``activation``); with ``cfg_net.bf16``, its matrix products in
    bfloat16 (:class:`Bfloat16Matmuls`)."""
    net = MLP(in_features=in_features, out_features=out_features, num_cells=list(cfg_net.hidden),
              activation_class=ACTIVATIONS[cfg_net.activation], device=device)
    return Bfloat16Matmuls(net) if cfg_net.get("bf16", False) else net


class Bfloat16Matmuls(nn.Module):
    """``net`` under ``torch.autocast`` to bfloat16, its output back in float32: the matrix products run at
    bfloat16's rate (CPUs with AVX512-BF16 or AMX, GPUs) with float32 accumulation, while everything downstream (the
    losses, log-probabilities, PPO's ratios) stays float32."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        with torch.autocast(inputs[0].device.type, dtype=torch.bfloat16):
            return self.net(*inputs).float()


#: The pixel networks' encoder when ``cfg_net.cnn`` leaves a key out: conv layers (output channels, kernel,
#: stride), ReLU after each; a linear layer to ``features``, LayerNorm and tanh; depth images are clipped at
#: ``depth_max`` [m] and scaled to [0, 1] (RGB: divided by 255).
CNN_DEFAULTS = {"channels": [16, 32], "kernels": [4, 3], "strides": [4, 2], "features": 64,
                "depth_max": 3.0}


class PixelNet(nn.Module):
    """A small CNN on ``pixels (..., C, H, W)`` (uint8 RGB or float depth), its features concatenated with the
    vector inputs (e.g. ``observation``, ``action``) and fed to an MLP head (``cfg_net.hidden``), then ``post``."""

    def __init__(self, pixel_spec, vector_dim: int, out_features: int, cfg_net: DictConfig, device,
                 post: nn.Module | None = None):
        super().__init__()
        cnn = {**CNN_DEFAULTS, **cfg_net.get("cnn", {})}
        c, h, w = pixel_spec.shape[-3:]
        self.rgb, self.depth_max = pixel_spec.dtype == torch.uint8, float(cnn["depth_max"])
        layers = []
        for out, k, stride in zip(cnn["channels"], cnn["kernels"], cnn["strides"]):
            layers += [nn.Conv2d(c, out, k, stride, device=device), nn.ReLU()]
            c = out
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            flat = self.conv(torch.zeros(1, pixel_spec.shape[-3], h, w, device=device)).shape[-1]
        self.project = nn.Sequential(nn.Linear(flat, cnn["features"], device=device),
                                     nn.LayerNorm(cnn["features"], device=device), nn.Tanh())
        self.head = mlp(cnn["features"] + vector_dim, out_features, cfg_net, device)
        self.post = post if post is not None else nn.Identity()

    def features(self, pixels: torch.Tensor) -> torch.Tensor:
        """The CNN's features of ``pixels (..., C, H, W)``: ``(..., cnn.features)``."""
        lead = pixels.shape[:-3]
        x = pixels.reshape(-1, *pixels.shape[-3:])
        x = x.float() / 255.0 if self.rgb else x.clamp(0.0, self.depth_max) / self.depth_max
        return self.project(self.conv(x)).reshape(*lead, -1)

    def forward(self, pixels: torch.Tensor, *vectors: torch.Tensor) -> torch.Tensor:
        return self.post(self.head(torch.cat((self.features(pixels), *vectors), -1)))


class StateProbe(nn.Module):
    """An auxiliary loss for a pixel policy trained in simulation: a linear read-out of the policy CNN's features,
    regressed on the env's ``privileged_state`` (normalised). Why: the policy gradient alone is a weak, noisy signal
    for learning to see; this one asks the policy's encoder directly for the state the images show (the pole's angle
    and, from the stacked frames, its rate), which a supervised probe learns in seconds (studies/pixel_probe.py)."""

    def __init__(self, encoder: PixelNet, state_dim: int, device):
        super().__init__()
        self.encoder = encoder
        self.readout = nn.Linear(encoder.project[0].out_features, state_dim, device=device)

    def forward(self, pixels: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return (self.readout(self.encoder.features(pixels)) - state).square().mean()


def make_state_probe(actor, env, coeff: float, device) -> StateProbe | None:
    """The :class:`StateProbe` of ``actor``'s CNN if ``coeff`` > 0, else None; refused for an env without
    ``privileged_state`` or a policy without a CNN."""
    if not coeff:
        return None
    encoders = [m for m in actor.modules() if isinstance(m, PixelNet)]
    if "privileged_state" not in env.observation_spec.keys() or not encoders:
        raise ValueError("algo.state_probe_coeff needs a pixel env that emits privileged_state (an env option, "
                         "pixel_privileged_state=True) and so a policy with a CNN")
    return StateProbe(encoders[0], env.observation_spec["privileged_state"].shape[-1], device)


def _inputs(env) -> tuple[list, int]:
    """The vector inputs of the networks (``observation``, if the env emits it) and their total size."""
    keys = [k for k in ("observation",) if k in env.observation_spec.keys()]
    return keys, sum(env.observation_spec[k].shape[-1] for k in keys)


#: ``cfg_net.distribution``: the action distribution of a continuous policy. ``normal`` leaves the env to clip
#: its samples to the action bounds (CleanRL's continuous PPO).
DISTRIBUTIONS = {"tanh_normal": TanhNormal, "normal": IndependentNormal}


def make_actor(env, cfg_net: DictConfig, device) -> ProbabilisticActor:
    """Gaussian policy on ``observation``: tanh-squashed (``cfg_net.distribution``, default ``tanh_normal``; its
    deterministic action is ``tanh(loc)``) or plain (``normal``), with a scale the network outputs per state or, if
    ``cfg_net.scale`` is ``parameter``, one learned per action dimension whatever the state (initially 1). An env
    with ``pixels`` gets a :class:`PixelNet` on the images and ``observation`` (if it emits one); a navigation env a
    categorical policy on depth and goal (``nav_policy.make_actor``)."""
    if nav_policy.is_nav_env(env):
        return nav_policy.make_actor(env, cfg_net, device, make_head=mlp)
    act_dim = env.action_spec.shape[-1]
    distribution, scale = cfg_net.get("distribution", "tanh_normal"), cfg_net.get("scale", "state")
    if distribution not in DISTRIBUTIONS or scale not in ("state", "parameter"):
        raise ValueError(f"policy_net.distribution must be one of {sorted(DISTRIBUTIONS)} (got {distribution!r}) "
                         f"and policy_net.scale 'state' or 'parameter' (got {scale!r})")
    if scale == "state":
        out_features, post = 2 * act_dim, NormalParamExtractor(scale_lb=1e-3)
    else:
        out_features, post = act_dim, AddStateIndependentNormalScale(act_dim, scale_lb=1e-3, device=device)
    if "pixels" in env.observation_spec.keys():
        keys, dim = _inputs(env)
        net = PixelNet(env.observation_spec["pixels"], dim, out_features, cfg_net, device, post=post)
        module = TensorDictModule(net, in_keys=["pixels", *keys], out_keys=["loc", "scale"])
    else:
        obs_dim = env.observation_spec["observation"].shape[-1]
        net = nn.Sequential(mlp(obs_dim, out_features, cfg_net, device), post)
        module = TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(module, in_keys=["loc", "scale"], spec=env.action_spec_unbatched,
                              distribution_class=DISTRIBUTIONS[distribution], return_log_prob=True)


def make_value(env, cfg_net: DictConfig, device, with_action: bool, actor=None) -> TensorDictModule:
    """V(observation) or, ``with_action``, Q(observation, action) (torchrl's MLP concatenates its inputs); with
    ``pixels``, a :class:`PixelNet` on the images and the vectors, unless the env emits ``privileged_state``: then an
    MLP on that (asymmetric actor-critic: in simulation the critic may read the state the policy has to see);
    for a navigation env, ``nav_policy.make_value`` (V only; on the trunk of ``actor`` if that is recurrent)."""
    if nav_policy.is_nav_env(env):
        if with_action:
            raise ValueError("navigation envs have discrete actions: train them with PPO (no Q-function)")
        return nav_policy.make_value(env, cfg_net, device, make_head=mlp, actor=actor)
    act_dim = env.action_spec.shape[-1]
    spec = env.observation_spec
    if "pixels" in spec.keys() and "privileged_state" not in spec.keys():
        keys, dim = _inputs(env)
        keys, dim = (keys + ["action"], dim + act_dim) if with_action else (keys, dim)
        net = PixelNet(spec["pixels"], dim, 1, cfg_net, device)
        out = ["state_action_value"] if with_action else ["state_value"]
        return ValueOperator(net, in_keys=["pixels", *keys], out_keys=out)
    key = "privileged_state" if "privileged_state" in spec.keys() else "observation"
    obs_dim = spec[key].shape[-1]
    if with_action:
        return ValueOperator(mlp(obs_dim + act_dim, 1, cfg_net, device), in_keys=[key, "action"],
                             out_keys=["state_action_value"])
    return ValueOperator(mlp(obs_dim, 1, cfg_net, device), in_keys=[key])
