"""Watch an env in the browser (3D, orbit with the mouse), or save a rollout as one self-contained HTML file.

    pip install -e '.[viewer]'                                               # viser, from this checkout
    python scripts/view.py --env ant                                         # random actions, live
    python scripts/view.py --policy outputs/ppo_ant/<run>/checkpoints/last.pt  # a trained policy, episodes on a loop
    python scripts/view.py --watch outputs/ppo_ant/<run>                     # a training run, live: reloads its
                                                                             # checkpoints/last.pt when rewritten
    python scripts/view.py --policy <ckpt> --save ant.html                   # one episode to a file; no server

The live modes print a URL (default http://127.0.0.1:8080, served to this machine only; on a remote machine forward
the port, e.g. ``ssh -L 8080:127.0.0.1:8080 host``, or serve every network interface with ``--host 0.0.0.0``, which
anyone who can reach the machine can then watch) and play env 0 in real time until Ctrl-C. A saved file holds
viser's client and the recording: open it in any browser from disk, without torchsim or Python (a playback bar
scrubs it).
"""

import argparse
import pathlib
import time

import numpy as np
import torch

import torchsim.envs
from torchsim.render import Scene
from torchsim.render.viewer import Viewer, save_html, trajectory


def load(checkpoint):
    """``(env, actor, env name)``: one env with the checkpoint's policy (deterministic), on the CPU."""
    from omegaconf import OmegaConf

    from torchsim.algos.checkpoints import load_checkpoint, load_policy
    from torchsim.algos.env_factory import make_env

    ckpt = load_checkpoint(checkpoint)
    cfg = OmegaConf.create(ckpt["cfg"])
    env = make_env(cfg, 1, "cpu")
    return env, load_policy(ckpt, env, "cpu"), cfg.env.name


def episode(env, actor, steps: int, on_step=None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Run one episode (at most ``steps`` steps; random actions where ``actor`` is None) and return env 0's ``q``
    trajectory ``(T, nq)`` and its mocap bodies' poses ``(T, K, 3)``, ``(T, K, 4)`` (a task's targets, which
    may move every step); ``on_step(base_env)`` after every step."""
    from torchrl.envs import ExplorationType, set_exploration_type

    base = getattr(env, "base_env", env)

    def record():  # the System's mocap poses: the model's (K, .) or per env (B, K, .) once a task has set them
        pos, quat = (x if x.ndim == 2 else x[0] for x in (base.sys.mocap_pos, base.sys.mocap_quat))
        qpos.append(base.state.q[0].double().numpy())
        mocap_pos.append(pos.double().numpy())
        mocap_quat.append(quat.double().numpy())

    qpos, mocap_pos, mocap_quat = [], [], []
    td = env.reset()
    record()
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(steps):
            if actor is None:
                td["action"] = env.action_spec.rand()
                td = env.step(td)
            else:
                td = env.step(actor(td))
            record()
            if on_step is not None:
                on_step(base)
            if td["next", "done"].any():
                break
            td = env.step_mdp(td)
    return np.stack(qpos), (np.stack(mocap_pos), np.stack(mocap_quat))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="ant", choices=torchsim.envs.list("physics"), help="with random actions")
    p.add_argument("--policy", default=None, help="a checkpoint (checkpoints/last.pt) to run")
    p.add_argument("--watch", default=None, help="a training run's directory: reload its last.pt when rewritten")
    p.add_argument("--save", default=None, help="write one episode to this HTML file instead of serving")
    p.add_argument("--steps", type=int, default=1000, help="steps per episode at most")
    p.add_argument("--episodes", type=int, default=0, help="live: stop after this many episodes (0: never)")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--host", default="127.0.0.1",
                   help="the address to serve on (default %(default)s: this machine only; 0.0.0.0: every network interface)")
    p.add_argument("--seed", type=int, default=0)
    return p


def modified(path: pathlib.Path) -> float | None:
    """``path``'s modification time, or None while it is missing (a training run renames last.pt to previous.pt
    just before it renames the new one to last.pt)."""
    try:
        return path.stat().st_mtime
    except FileNotFoundError:
        return None


def main():
    args = parser().parse_args()
    torch.manual_seed(args.seed)
    checkpoint = args.policy or (pathlib.Path(args.watch) / "checkpoints" / "last.pt" if args.watch else None)
    if checkpoint is not None:
        checkpoint = pathlib.Path(checkpoint)
        while not checkpoint.exists():  # a run that has not written its first checkpoint yet
            print(f"waiting for {checkpoint}", flush=True)
            time.sleep(5)
        stamp = modified(checkpoint)  # before loading: a checkpoint written meanwhile is loaded next
        env, actor, name = load(checkpoint)
    else:
        env, actor, name = torchsim.envs.make(args.env, num_envs=1), None, args.env
    base = getattr(env, "base_env", env)
    scene = Scene.build(base.mj_model, base.sys, skip_unsupported=True)
    if scene.skipped:
        print(f"not drawn (meshes, height fields): {', '.join(scene.skipped)}")
    if args.save:
        qpos, mocap = episode(env, actor, args.steps)
        path = save_html(scene, trajectory(base.sys, qpos), args.save, dt=base.dt, mocap=mocap)
        print(f"wrote {path} ({len(qpos)} frames of {name}, {path.stat().st_size / 1e6:.1f} MB)")
        return
    viewer = Viewer(scene, host=args.host, port=args.port)
    viewer.frame(poses=base.state)
    print(f"viewing {name}: open {viewer.url}", flush=True)

    def show(b, clock=[time.perf_counter()]):  # real time: one env step per dt
        viewer.update(b.state, mocap_pos=b.sys.mocap_pos, mocap_quat=b.sys.mocap_quat)  # a task's mocap targets
        time.sleep(max(0.0, clock[0] + b.dt - time.perf_counter()))
        clock[0] = time.perf_counter()

    try:
        done = 0
        while not args.episodes or done < args.episodes:
            if args.watch and modified(checkpoint) not in (None, stamp):
                stamp = modified(checkpoint)
                env, actor, _ = load(checkpoint)
                base = env.base_env
                print(f"reloaded {checkpoint}", flush=True)
            qpos, _ = episode(env, actor, args.steps, on_step=show)
            done += 1
            print(f"episode {done}: {len(qpos) - 1} steps", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()


if __name__ == "__main__":
    main()
