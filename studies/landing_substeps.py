"""Where a policy's launches come from: the visited state whose torso torchsim throws up hardest, against MuJoCo,
stepped at several substep lengths, with and without friction.

    python studies/landing_substeps.py <run>/checkpoints/last.pt [--steps 30] [--substeps 20 80 320]

The policy runs ``--steps`` steps in its own env (``transfer_step_error.visited``); of the states it visits, the one
where one env step of torchsim's soft contacts leaves the root's vertical speed furthest above MuJoCo's converged
answer (MuJoCo at a twentieth of the model's step) is replayed with its action for one env step. Printed every 10
ms: the root's vertical speed [m/s] in MuJoCo (converged) and in torchsim (soft and impulse contacts) at each
``--substeps`` per model step, once as the model is and once frictionless (every geom condim 1, both simulators).
A model whose answer moves as the substep shrinks has not converged; one that converges to MuJoCo's answer is
only too coarse.
"""

import argparse

import mujoco
import numpy as np
import torch

import torchsim
from transfer_step_error import edited_model, mujoco_step, torchsim_step, visited

REPORT_EVERY_S = 0.01


def mujoco_trace(xml: str, q, qd, ctrl, frame_skip: int, split: int = 20) -> list[float]:
    model = mujoco.MjModel.from_xml_string(xml)
    model.opt.timestep /= split
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = q.numpy(), qd.numpy(), ctrl.numpy()
    every = round(REPORT_EVERY_S / model.opt.timestep)
    trace = []
    for i in range(split * frame_skip):
        mujoco.mj_step(model, data)
        if (i + 1) % every == 0:
            trace.append(float(data.qvel[2]))
    return trace


def torchsim_trace(xml: str, contact_model: str, substeps: int, q, qd, ctrl, frame_skip: int) -> list[float]:
    sys = torchsim.load_mjcf(xml, dtype=torch.float64, contact_model=contact_model, substeps=substeps)
    state = torchsim.init(sys, q[None], qd[None])
    every = round(REPORT_EVERY_S / sys.timestep)
    trace = []
    for i in range(frame_skip):
        state = torchsim.step(sys, state, ctrl[None])
        if (i + 1) % every == 0:
            trace.append(float(state.qd[0, 2]))
    return trace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--substeps", type=int, nargs="+", default=[20, 80, 320])
    args = parser.parse_args()
    q, qd, ctrl, env = visited(args.checkpoint, args.steps)
    if env.mj_model.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        raise SystemExit("this study follows a free root's vertical speed (qd[2]); the model's root is not free")
    spec = edited_model(env, False, False)
    model, xml = spec.compile(), spec.to_xml()
    ref_qd = mujoco_step(model, 20, env.frame_skip, q, qd, ctrl)[1]
    soft_qd = torchsim_step(xml, "soft", env.frame_skip, q, qd, ctrl)[1]
    worst = int(torch.argmax(soft_qd[:, 2] - ref_qd[:, 2]))
    q, qd, ctrl = q[worst], qd[worst], ctrl[worst]
    print(f"{len(ref_qd)} states; the worst: root height {q[2]:.3f} m, vertical speed {qd[2]:+.2f} m/s "
          f"(after the env step: MuJoCo {ref_qd[worst, 2]:+.2f}, torchsim soft {soft_qd[worst, 2]:+.2f})\n")
    for frictionless in (False, True):
        xml_case = edited_model(env, False, frictionless).to_xml()
        rows = {"MuJoCo, converged": mujoco_trace(xml_case, q, qd, ctrl, env.frame_skip)}
        for contact_model in ("soft", "impulse"):
            for substeps in args.substeps:
                name = f"torchsim {contact_model}, {1e6 * model.opt.timestep / substeps:.0f} us substeps"
                rows[name] = torchsim_trace(xml_case, contact_model, substeps, q, qd, ctrl, env.frame_skip)
        times = [f"{1000 * REPORT_EVERY_S * (i + 1):.0f} ms" for i in range(len(rows["MuJoCo, converged"]))]
        print(("frictionless" if frictionless else "as the model is") + ": the root's vertical speed [m/s]\n")
        print("| physics | " + " | ".join(times) + " |\n|---|" + "---:|" * len(times))
        for name, trace in rows.items():
            print(f"| {name} | " + " | ".join(f"{v:+.2f}" for v in np.asarray(trace)) + " |")
        print()


if __name__ == "__main__":
    main()
