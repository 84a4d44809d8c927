"""A PointNav PPO run (``python -m torchsim.train env=pointnav ...``) from its checkpoint: the training curve (the
run's held-out evaluations' success and SPL, evaluation and training return, against env steps, wall-clock minutes
on the top axis) as a PNG with the evaluations as a CSV next to it; and, with ``--episodes N``, a final evaluation
of the checkpoint's policy on N held-out episodes (``env.eval_split``), with the most probable action and with
sampled actions; with ``--video DIR``, GIFs of the most-probable-action policy's first successful and first failed
held-out episodes (seeds 0, 1, ...; the map from above beside the depth view, ``torchsim.envs.nav.video``):

    python studies/pointnav_report.py outputs/ppo_pointnav/main/checkpoints/last.pt docs/media/pointnav_training.png \
        --episodes 256 --video docs/media
"""

import argparse
import pathlib

import matplotlib
import numpy as np
from omegaconf import OmegaConf

from torchsim.algos.checkpoints import load_checkpoint, load_policy
from torchsim.algos.env_factory import make_env
from torchsim.algos.evaluation import evaluate
from torchsim.algos.outputs import video

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint")
    p.add_argument("out", help="the PNG; the CSV gets the same name with .csv")
    p.add_argument("--title", default=None)
    p.add_argument("--episodes", type=int, default=0, help="held-out episodes of the final evaluation (0: none)")
    p.add_argument("--seed", type=int, default=1, help="the final evaluation's episode seed")
    p.add_argument("--video", default=None, help="folder for pointnav_success.gif and pointnav_failure.gif")
    args = p.parse_args()
    ckpt = load_checkpoint(args.checkpoint)
    h, cfg = ckpt["history"], ckpt["cfg"]
    ev, success, spl = (np.array(h[k]).reshape(-1, 3) for k in ("eval", "eval_success", "eval_spl"))
    train = np.array(h["train"]).reshape(-1, 3)
    fig, (ax_metric, ax_return) = plt.subplots(1, 2, figsize=(12, 4))
    ax_metric.plot(success[:, 0], success[:, 2], "o-", label="success (held-out)")
    ax_metric.plot(spl[:, 0], spl[:, 2], "s-", label="SPL (held-out)")
    ax_metric.set_ylim(-0.02, 1.02)
    ax_metric.set_ylabel("rate")
    ax_return.plot(train[:, 0], train[:, 2], "-", alpha=0.7, label="train return (last 100 episodes)")
    ax_return.plot(ev[:, 0], ev[:, 2], "o-", label="eval return (held-out)")
    ax_return.set_ylabel("return")
    for ax in (ax_metric, ax_return):
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
        ax.legend()
        top = ax.secondary_xaxis("top", functions=(
            lambda s: np.interp(s, ev[:, 0], ev[:, 1] / 60), lambda m: np.interp(m, ev[:, 1] / 60, ev[:, 0])))
        top.set_xlabel("wall-clock (min)")
    a = cfg["algo"]
    fig.suptitle(args.title or f"PPO PointNav: {a['num_envs']} envs x {a['unroll']} steps, "
                 f"{cfg['eval']['episodes']} held-out ({cfg['env']['eval_split']}) episodes per evaluation")
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    rows = np.column_stack([ev[:, 0], ev[:, 1], ev[:, 2], success[:, 2], spl[:, 2]])
    np.savetxt(pathlib.Path(args.out).with_suffix(".csv"), rows, delimiter=",",
               fmt=["%d", "%.1f", "%.3f", "%.4f", "%.4f"], header="env_steps,wall_s,eval_return,success,spl",
               comments="")
    print(f"wrote {args.out} and its .csv: {len(ev)} evaluations, last: success {success[-1, 2]:.3f}, "
          f"SPL {spl[-1, 2]:.3f} at {int(ev[-1, 0]):,} env steps")
    if args.episodes:
        final_evaluation(ckpt, args.episodes, args.seed)
    if args.video:
        videos(ckpt, pathlib.Path(args.video))


def final_evaluation(ckpt: dict, episodes: int, seed: int) -> None:
    cfg = OmegaConf.create(ckpt["cfg"])
    env = make_env(cfg, episodes, "cpu")
    actor = load_policy(ckpt, env, "cpu")
    for deterministic in (True, False):
        r = evaluate(env, actor, cfg.env.episode_length, seed=seed, deterministic=deterministic)
        print(f"{episodes} held-out ({cfg.env.eval_split}) episodes, seed {seed}, "
              f"{'most probable action' if deterministic else 'sampled actions'}: success "
              f"{r.success.float().mean().item():.3f}, SPL {r.spl.mean().item():.3f}, return "
              f"{r.ret.mean().item():.2f}, episode length {r.length.float().mean().item():.0f} "
              f"(trained {ckpt['counters']['env_steps']:,} env steps)")


def videos(ckpt: dict, out_dir: pathlib.Path, max_seeds: int = 40) -> None:
    """GIFs of the checkpoint's first successful and first failed held-out episode (most probable action, episode
    seeds 0, 1, ... up to ``max_seeds``), as ``pointnav_success.gif`` and ``pointnav_failure.gif`` in ``out_dir``."""
    cfg = OmegaConf.create(ckpt["cfg"])
    env = make_env(cfg, 1, "cpu")
    actor = load_policy(ckpt, env, "cpu")
    wanted = {True: "pointnav_success.gif", False: "pointnav_failure.gif"}
    for seed in range(max_seeds):
        r = evaluate(env, actor, cfg.env.episode_length, record=True, seed=seed)
        name = wanted.pop(bool(r.success[0]), None)
        if name:
            video(env, cfg.env.name, r.trajectory, out_dir / name)
            print(f"{name}: held-out episode seed {seed}, {len(r.trajectory) - 1} steps, start geodesic "
                  f"{r.trajectory[0].geodesic:.2f} m, end {r.trajectory[-1].geodesic:.2f} m, SPL {r.spl[0].item():.3f}")
        if not wanted:
            break
    for name in wanted.values():
        print(f"no {name} in {max_seeds} held-out episodes")


if __name__ == "__main__":
    main()
