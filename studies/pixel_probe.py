"""How well can the pixel policy's CNN read the pendulum's state from its images? A supervised probe.

    OMP_NUM_THREADS=1 python studies/pixel_probe.py --frame-stack 2
    OMP_NUM_THREADS=1 python studies/pixel_probe.py --frame-stack 4

Collects ``--steps`` steps of ``inverted_pendulum_pixels`` at 256 envs under uniform random actions (episodes end
when the pole falls past 0.2 rad, so the images cover the balancing range), with the pole's true angle [rad] and
rate [rad/s] beside each stack of frames; trains the recipe's encoder (``algos.networks.PixelNet``, the
``tuned/ppo_inverted_pendulum_pixels.yaml`` policy network) by regression on both (standardised), 1,500 Adam
steps of 256; and prints the held-out (4,096 samples) RMS errors, overall and where |angle| < 0.1 rad. The errors
bound what a PPO policy on that encoder can know: the angle comes from one frame, the rate only from the difference
between frames ``dt`` = 40 ms apart.
"""

import argparse
import time

import torch
from omegaconf import OmegaConf

import torchsim.algos
import torchsim.envs
from torchsim.algos.networks import PixelNet


def collect(frame_stack: int, steps: int, envs: int = 256):
    """Stacks of frames ``(N, frame_stack, H, W)`` and the pole's (angle, rate) ``(N, 2)`` after each step."""
    env = torchsim.envs.make("inverted_pendulum_pixels", envs, frame_stack=frame_stack, native_autoreset=True,
                               render_compile=False)
    td = env.reset()
    frames, labels = [], []
    for _ in range(steps):
        td["action"] = 2 * torch.rand(envs, 1) - 1
        td = env.step_mdp(env.step(td))
        frames.append(td["pixels"])
        labels.append(torch.stack((env.state.q[:, 1], env.state.qd[:, 1]), -1))
    return torch.cat(frames), torch.cat(labels)


def probe(frames, labels, net_cfg, iterations=1500, batch=256, test=4096):
    """Held-out RMS errors of angle and rate: overall, and where |angle| < 0.1 rad; and that subset's std."""
    order = torch.randperm(len(frames))
    train, held_out = order[:-test], order[-test:]
    scale = labels.std(0)
    spec = torchsim.envs.make("inverted_pendulum_pixels", 1, frame_stack=frames.shape[1],
                              render_compile=False).observation_spec
    net = PixelNet(spec["pixels"], 0, 2, net_cfg, "cpu")
    optim = torch.optim.Adam(net.parameters(), 1e-3)
    for _ in range(iterations):
        idx = train[torch.randint(len(train), (batch,))]
        loss = (net(frames[idx]) - labels[idx] / scale).square().mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    with torch.no_grad():
        error = net(frames[held_out]) * scale - labels[held_out]
    upright = labels[held_out, 0].abs() < 0.1
    rms = lambda e: e.square().mean(0).sqrt()  # noqa: E731
    return rms(error), rms(error[upright]), labels[held_out][upright].std(0)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frame-stack", type=int, default=4)
    parser.add_argument("--steps", type=int, default=120, help="env steps collected (x 256 envs)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    recipe = OmegaConf.load(f"{torchsim.algos.__path__[0]}/configs/tuned/ppo_inverted_pendulum_pixels.yaml")
    start = time.time()
    frames, labels = collect(args.frame_stack, args.steps)
    overall, upright, spread = probe(frames, labels, recipe.algo.policy_net)
    print(f"frame_stack {args.frame_stack}, {len(frames)} samples, {time.time() - start:.0f} s; held-out RMS error: "
          f"angle {overall[0]:.4f} rad, rate {overall[1]:.3f} rad/s; where |angle| < 0.1 rad: angle "
          f"{upright[0]:.4f} rad, rate {upright[1]:.3f} rad/s (their spread there: {spread[0]:.4f} rad, "
          f"{spread[1]:.3f} rad/s)")


if __name__ == "__main__":
    main()
