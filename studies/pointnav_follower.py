"""PointNav sanity check and env throughput (docs/navigation.md).

1. The scripted shortest-path follower (``PointNav.shortest_path_action``) on held-out layouts (``split="test"``):
   success rate and SPL over ``--episodes`` episodes (each env's first episode, so none is favoured by being short).
2. Env frames/s (reset + step + depth render, no policy): random actions (STOP with probability ``--p-stop``, the
   others uniform), ``step_and_maybe_reset`` as a collector runs it, per batch size and thread count.

    OMP_NUM_THREADS=1 python studies/pointnav_follower.py --episodes 256 --batches 1 64 256 1024 --threads 1 2
    python studies/pointnav_follower.py --figures docs/media     # the layout and depth pictures of the docs
"""

import argparse
import json
import math
import time

import torch

from torchsim.envs.nav import PointNav
from torchsim.envs.nav.pointnav import FORWARD, STOP


def follower_eval(episodes: int, num_layouts: int, seed: int) -> dict:
    """Success and SPL of the follower over ``episodes`` first episodes (one per env) on held-out layouts."""
    env = PointNav(episodes, num_layouts=num_layouts, split="test", seed=seed)
    td = env.reset()
    finished = torch.zeros(episodes, dtype=torch.bool)
    success = torch.zeros(episodes)
    spl = torch.zeros(episodes)
    path_ratio = torch.zeros(episodes)
    start_geo = env.start_geo.clone()
    steps = torch.zeros(episodes)
    for _ in range(env.episode_length):
        td["action"] = env.shortest_path_action()
        td = env.step(td)
        nxt = td["next"]
        done = nxt["done"].squeeze(-1) & ~finished
        success[done] = nxt["success"].squeeze(-1)[done].float()
        spl[done] = nxt["spl"].squeeze(-1)[done]
        path_ratio[done] = env.path_len[done] / start_geo[done]
        steps[done] = env.step_count[done].float()
        finished |= done
        if finished.all():
            break
        td = td["next"].clone()
    return dict(episodes=episodes, success=success.mean().item(), spl=spl.mean().item(),
                spl_min=spl.min().item(), mean_geodesic_m=start_geo.mean().item(),
                max_geodesic_m=start_geo.max().item(), mean_steps=steps.mean().item(),
                path_over_geodesic_median=path_ratio.median().item(),
                path_over_geodesic_min=path_ratio.min().item())


def throughput(batch: int, threads: int, steps: int, p_stop: float, seed: int = 0) -> dict:
    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    env = PointNav(batch, num_layouts=64, seed=seed)
    build = time.perf_counter() - t0
    td = env.reset()

    def actions():
        a = torch.randint(FORWARD, 4, (batch,), generator=gen)
        return torch.where(torch.rand(batch, generator=gen) < p_stop, STOP, a)

    for _ in range(3):     # warm-up
        td["action"] = actions()
        _, td = env.step_and_maybe_reset(td)
    episodes = 0
    t0 = time.perf_counter()
    for _ in range(steps):
        td["action"] = actions()
        out, td = env.step_and_maybe_reset(td)
        episodes += int(out["next", "done"].sum())
    dt = time.perf_counter() - t0
    return dict(batch=batch, threads=threads, steps=steps, frames_per_s=batch * steps / dt,
                ms_per_step=1e3 * dt / steps, episodes_ended=episodes, build_s=build)


def figures(out_dir: str) -> None:
    import pathlib

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    env = PointNav(4, num_layouts=4, split="test", seed=3)
    td = env.reset()
    b = 0
    l, g, c = int(env.layout[b]), env.size, env.cell
    path = [env.pos[b].clone()]
    depth0, pose0 = env.depth[b, 0].clone(), (env.pos[b].clone(), env.heading[b].item())
    for _ in range(env.episode_length):
        td["action"] = env.shortest_path_action()
        td = env.step(td)
        path.append(env.pos[b].clone())
        if td["next", "done"][b]:
            break
        td = td["next"].clone()
    path = torch.stack(path)
    field = env.field[b].reshape(g, g).clone()
    fig, ax = plt.subplots(1, 2, figsize=(11, 5))
    ext = (0, g * c, 0, g * c)
    f = torch.where(torch.isfinite(field), field, torch.nan)
    ax[0].imshow(f.numpy(), origin="lower", extent=ext, cmap="viridis")
    ax[0].imshow(env.walls[l].float().numpy(), origin="lower", extent=ext, cmap="gray_r",
                 alpha=env.walls[l].float().numpy())
    ax[0].plot(path[:, 0], path[:, 1], "r-", lw=1.5, label="follower's path")
    ax[0].plot(*path[0], "wo", mec="k", label="start")
    p, h = pose0
    ax[0].arrow(p[0], p[1], 0.6 * math.cos(h), 0.6 * math.sin(h), color="w", width=0.05)
    ax[0].plot(*env.goal[b], "r*", ms=14, mec="k", label="goal")
    ax[0].set_title(f"layout seed {env.layout_seeds[l]} (walls black, geodesic distance to goal in colour)",
                    fontsize=9)
    ax[0].set_xlabel("x [m]")
    ax[0].set_ylabel("y [m]")
    ax[0].legend(loc="lower right", fontsize=8)
    im = ax[1].imshow(depth0.numpy(), cmap="magma_r", vmin=0, vmax=env.max_depth)
    ax[1].set_title("64x64 depth at the start (white arrow) [m]", fontsize=9)
    fig.colorbar(im, ax=ax[1], fraction=0.046)
    fig.tight_layout()
    fig.savefig(out / "pointnav_layout_depth.png", dpi=110)
    fig, axs = plt.subplots(2, 4, figsize=(12, 6))
    for k, a in enumerate(axs.flat):
        from torchsim.envs.nav.layouts import generate_layout
        a.imshow(generate_layout(2_000_000 + k, g).float().numpy(), origin="lower", extent=ext, cmap="gray_r")
        a.set_title(f"seed {2_000_000 + k}", fontsize=8)
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle(f"held-out layouts ({g}x{g} cells of {c} m)")
    fig.tight_layout()
    fig.savefig(out / "pointnav_layouts.png", dpi=90)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=256)
    p.add_argument("--layouts", type=int, default=64, help="held-out layouts resident for the follower")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batches", type=int, nargs="*", default=[1, 64, 256, 1024])
    p.add_argument("--threads", type=int, nargs="*", default=[1, 2])
    p.add_argument("--frames", type=int, default=20000, help="frames per throughput measurement (>= 20 steps)")
    p.add_argument("--p-stop", type=float, default=0.02)
    p.add_argument("--figures", default=None, help="write the docs' pictures into this folder")
    args = p.parse_args()
    if args.figures:
        figures(args.figures)
    if args.episodes:
        t0 = time.perf_counter()
        r = follower_eval(args.episodes, args.layouts, args.seed)
        r["seconds"] = time.perf_counter() - t0
        print(json.dumps({"follower": r}))
    for threads in args.threads:
        for batch in args.batches:
            steps = max(20, args.frames // batch)
            print(json.dumps({"throughput": throughput(batch, threads, steps, args.p_stop, args.seed)}), flush=True)


if __name__ == "__main__":
    main()
