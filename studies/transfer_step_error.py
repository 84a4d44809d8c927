"""Where a trained policy's transfer gap comes from: one env step from the states the policy visits, on torchsim's
physics and on MuJoCo's, against MuJoCo's converged answer.

    python studies/transfer_step_error.py <run>/checkpoints/last.pt [--steps 100] [--contact-models impulse soft]
        [--no-floor | --frictionless]

The policy runs ``--steps`` steps in its own env (64 envs, deterministic actions); every state and action it
visits (torso height inside the healthy range) is then stepped once more, in float64, by torchsim with each
``--contact-models`` and by MuJoCo C at the model's time step, at a quarter of it and at a twentieth (the
reference); then torchsim's against MuJoCo at the model's step. Printed per part of ``qd`` (the root's linear and
angular velocity, the joint rates): the median error of ``qd`` after the env step relative to the median change of
``qd`` over it, the median error of the root's height [mm] and the 99th percentile of the error of the root's
vertical speed [m/s] (where launches show).
``--no-floor`` removes every contact with the floor on both sides, ``--frictionless`` gives every
contact condim 1 on both: what is left of the gap without contacts or without friction.
"""

import argparse
import sys
from pathlib import Path

import mujoco
import mujoco.rollout
import numpy as np
import torch
from omegaconf import OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

import torchsim
from torchsim.algos.checkpoints import load_checkpoint, load_policy
from torchsim.algos.env_factory import make_env

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))  # the benchmarks' MuJoCo helpers
from _timing import mujoco_start_states  # noqa: E402

#: The parts of ``qd`` reported: a free root's 3 + 3 rates, or a planar root's (x and z slides, a hinge about y).
PARTS = {"root velocity": slice(0, 3), "root angular velocity": slice(3, 6), "joint rates": slice(6, None)}
PLANAR_PARTS = {"root velocity": slice(0, 2), "root angular velocity": slice(2, 3), "joint rates": slice(3, None)}


def visited(checkpoint: str, steps: int):
    """The states ``q, qd`` and clipped actions the policy visits (float64), its env and its task's frame skip."""
    ckpt = load_checkpoint(checkpoint, "cpu")
    env = make_env(OmegaConf.create(ckpt["cfg"]), 64, "cpu")
    actor = load_policy(ckpt, env, "cpu")
    torch.manual_seed(7)
    td, rows = env.reset(), []
    alive = torch.ones(env.batch_size, dtype=torch.bool)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(steps):
            td = actor(td)
            state = env.base_env.state
            rows.append([x[alive] for x in (state.q.double(), state.qd.double(), td["action"].double().clamp(-1, 1))])
            td = env.step(td)
            alive &= ~td["next", "done"].squeeze(-1)  # a finished episode's env is not reset here: its states stop
            td = step_mdp(td)
    q, qd, ctrl = (torch.cat(x) for x in zip(*rows))
    return q, qd, ctrl, env.base_env


def edited_model(env, no_floor: bool, frictionless: bool) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_string(env._model_xml())
    for geom in spec.geoms:
        if no_floor and geom.type == mujoco.mjtGeom.mjGEOM_PLANE:
            geom.contype, geom.conaffinity = 0, 0
        if frictionless:
            geom.condim = 1
    return spec


def mujoco_step(model: mujoco.MjModel, split: int, frame_skip: int, q, qd, ctrl):
    """``q, qd`` after one env step in MuJoCo with the model's step split in ``split``."""
    timestep = model.opt.timestep
    model.opt.timestep = timestep / split
    datas = [mujoco.MjData(model) for _ in range(torch.get_num_threads())]
    start = mujoco_start_states(model, q.numpy(), qd.numpy())
    n = split * frame_skip
    out = np.empty((q.shape[0], n, start.shape[1]))
    mujoco.rollout.rollout(model, datas, start, np.repeat(ctrl.numpy()[:, None], n, 1), nstep=n, state=out)
    model.opt.timestep = timestep
    end = torch.as_tensor(out[:, -1])  # FULLPHYSICS: time, qpos, qvel, ...
    return end[:, 1:1 + model.nq], end[:, 1 + model.nq:1 + model.nq + model.nv]


def torchsim_step(xml: str, contact_model: str, frame_skip: int, q, qd, ctrl):
    sys = torchsim.load_mjcf(xml, dtype=torch.float64, contact_model=contact_model)
    state = torchsim.init(sys, q, qd)
    for _ in range(frame_skip):
        state = torchsim.step(sys, state, ctrl)
    return state.q, state.qd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--contact-models", nargs="+", default=["impulse", "soft"])
    edit = parser.add_mutually_exclusive_group()
    edit.add_argument("--no-floor", action="store_true")
    edit.add_argument("--frictionless", action="store_true")
    args = parser.parse_args()
    q, qd, ctrl, env = visited(args.checkpoint, args.steps)
    free_root = env.mj_model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    root_z = 2 if free_root else 1  # a free root's z, or a planar root's
    parts = PARTS if free_root else PLANAR_PARTS
    spec = edited_model(env, args.no_floor, args.frictionless)
    model = spec.compile()
    xml = spec.to_xml()
    converged = mujoco_step(model, 20, env.frame_skip, q, qd, ctrl)
    at_step = mujoco_step(model, 1, env.frame_skip, q, qd, ctrl)
    change = (converged[1] - qd)

    def report(name, result, reference):
        err = result[1] - reference[1]
        cells = [f"{(err[:, s].norm(dim=-1).median() / change[:, s].norm(dim=-1).median()).item():.2g}"
                 for s in parts.values()]
        z_mm = 1000 * (result[0][:, root_z] - reference[0][:, root_z]).abs().median().item()
        rise_tail = (err[:, root_z]).abs().quantile(0.99).item()  # rare launches hide from the medians
        print(f"| {name} | " + " | ".join(cells) + f" | {z_mm:.2g} | {rise_tail:.2g} |")

    header = ("| physics | " + " | ".join(parts) + " | root height [mm] | root vertical speed, 99th percentile [m/s] |"
              + "\n|---|" + "---:|" * (len(parts) + 2))
    ours = {name: torchsim_step(xml, name, env.frame_skip, q, qd, ctrl) for name in args.contact_models}
    print(f"{q.shape[0]} states; one env step against MuJoCo at a twentieth of the model's time step\n\n{header}")
    report("MuJoCo at the model's step", at_step, converged)
    report("MuJoCo at a quarter of it", mujoco_step(model, 4, env.frame_skip, q, qd, ctrl), converged)
    for name, result in ours.items():
        report(f"torchsim, {name} contacts", result, converged)
    print(f"\nthe same against MuJoCo at the model's step (what a policy meets when it moves to MuJoCo)\n\n{header}")
    for name, result in ours.items():
        report(f"torchsim, {name} contacts", result, at_step)


if __name__ == "__main__":
    main()
