"""Evaluate (and render) a trained policy: ``python -m torchsim.evaluate checkpoint=<run>/checkpoints/last.pt
[episodes=N] [max_steps=N] [video=true] [device=cpu] [seed=N] [physics=torchsim|mujoco] [mujoco_substeps=N]``.

Prints the deterministic policy's mean return and episode length over ``episodes`` envs (default: as many as the
run's own evaluations, ``eval.episodes``) (and, for goal-reaching
tasks, the success rate and median final goal distance; for navigation, success rate and SPL on the held-out
layouts of ``env.eval_split``); ``seed`` fixes the episodes' start states (a run's own evaluations use its
``eval.seed``); ``video=true`` writes ``eval.gif`` of env 0 next to the checkpoint's run dir (for navigation: the
map from above beside the depth view). ``physics=mujoco`` runs the same task code on MuJoCo C's
physics (``torchsim.execution.mujoco``): a policy trained in torchsim, evaluated in MuJoCo (default: the physics it
trained on); ``mujoco_substeps=N`` splits MuJoCo's model timestep into N steps, the control held (default: as the run
trained, else 1).
"""

import pathlib
import sys

from omegaconf import OmegaConf

from torchsim.algos.checkpoints import load_checkpoint, load_policy
from torchsim.algos.env_factory import make_env
from torchsim.algos.evaluation import evaluate
from torchsim.algos.outputs import video

DEFAULTS = {"checkpoint": "???", "episodes": None, "max_steps": None, "video": False, "device": "cpu", "seed": None,
            "physics": None, "mujoco_substeps": None}


def parse(argv: list[str]):
    """The ``key=value`` arguments over :data:`DEFAULTS`; ``-h``/``--help`` prints the usage, and an argument that
    is not ``key=value`` for one of its keys, or no checkpoint, exits naming it."""
    if {"-h", "--help"} & set(argv):
        print(__doc__)
        raise SystemExit(0)
    keys = ", ".join(DEFAULTS)
    for arg in argv:
        if arg.partition("=")[0] not in DEFAULTS or "=" not in arg:
            raise SystemExit(f"torchsim.evaluate: '{arg}' is not key=value for one of its keys ({keys})")
    args = OmegaConf.merge(OmegaConf.create(DEFAULTS), OmegaConf.from_cli(argv))
    if OmegaConf.is_missing(args, "checkpoint"):
        raise SystemExit("torchsim.evaluate: give the policy to run, checkpoint=<run>/checkpoints/last.pt")
    return args


def main(argv: list[str]) -> dict:
    args = parse(argv)
    ckpt = load_checkpoint(args.checkpoint, args.device)
    cfg = OmegaConf.create(ckpt["cfg"])
    trained_on = cfg.get("physics", "torchsim")
    cfg.physics = args.physics or trained_on
    if args.mujoco_substeps is not None:
        if cfg.physics != "mujoco":
            raise SystemExit("torchsim.evaluate: mujoco_substeps splits MuJoCo's step: it needs physics=mujoco")
        cfg.mujoco_substeps = args.mujoco_substeps
    env = make_env(cfg, args.episodes or cfg.eval.episodes, args.device)
    actor = load_policy(ckpt, env, args.device)
    ev = evaluate(env, actor, args.max_steps or cfg.eval.max_steps, record=args.video, seed=args.seed)
    result = {"env": cfg.env.name, "algo": cfg.algo.name, "env_steps_trained": ckpt["counters"]["env_steps"],
              "trained_on": trained_on, "physics": cfg.physics,
              **({"mujoco_substeps": cfg.get("mujoco_substeps", 1)} if cfg.physics == "mujoco" else {}),
              "return_mean": ev.ret.mean().item(), "return_std": ev.ret.std().item(),
              "episode_length_mean": ev.length.float().mean().item()}
    if ev.final_distance is not None:
        result["success_rate"] = ev.success_rate(env.base_env.success_distance)
        result["final_distance_median"] = ev.final_distance.median().item()
    if ev.spl is not None:
        result["success_rate"] = ev.success.float().mean().item()
        result["spl"] = ev.spl.mean().item()
    print(result)
    if args.video:
        video(env, cfg.env.name, ev.trajectory, pathlib.Path(args.checkpoint).parent.parent / "eval.gif")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
