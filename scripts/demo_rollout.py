"""Demo: batched random-control rollout of the MJCF Ant with torchsim.

    python scripts/demo_rollout.py --method spring --num-envs 64 --seconds 0.5

Starts every env from the model's "home" keyframe with +-0.05 rad of noise on the hinges.
"""

import argparse
import pathlib
import time

import mujoco
import torch

import torchsim

ANT_XML = pathlib.Path(__file__).resolve().parent.parent / "envs" / "assets" / "ant.xml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", choices=["spring", "xpbd"], default="spring")
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=0.5, help="simulated time")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    torch.manual_seed(args.seed)
    system = torchsim.load_mjcf(str(ANT_XML), method=args.method)
    if args.device != "cpu":
        system = system.to(args.device)
    device = torch.device(args.device)
    B, dt = args.num_envs, float(system.timestep)
    n_steps = max(1, round(args.seconds / dt))
    report_every = max(1, round(0.1 / dt))
    print(f"ant: method={args.method} envs={B} nq={system.nq} nv={system.nv} nu={system.nu} "
          f"dt={dt:g}s substeps={system.substeps} contact pairs={system.num_contact_pairs} "
          f"(points {system.num_contacts}) steps={n_steps} device={device}")

    home = torch.as_tensor(mujoco.MjModel.from_xml_path(str(ANT_XML)).key_qpos[0], dtype=system.dtype)
    q = home.to(device).expand(B, -1).clone()
    q[:, 7:] += 0.05 * (2 * torch.rand(B, system.nq - 7, device=device, dtype=q.dtype) - 1)
    qd = torch.zeros(B, system.nv, device=device, dtype=q.dtype)
    with torch.no_grad():
        state = torchsim.init(system, q, qd)
        t0 = time.perf_counter()
        for i in range(1, n_steps + 1):
            ctrl = torch.rand(B, system.nu, device=device, dtype=q.dtype) * 2.0 - 1.0
            state = torchsim.step(system, state, ctrl)
            if i % report_every == 0 or i == n_steps:
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                elapsed = time.perf_counter() - t0
                height = state.x_pos[:, 0, 2].mean().item()
                diverged = int(state.diverged.sum().item())
                print(f"t={i * dt:6.2f}s  steps/s={i / elapsed:9.1f}  env-steps/s={i * B / elapsed:11.1f}  "
                      f"torso_z={height:.3f}  diverged={diverged}/{B}")
    print(f"done: {n_steps} steps x {B} envs ({n_steps * dt:.2f}s sim) in {elapsed:.2f}s wall, "
          f"{n_steps * B / elapsed:.1f} env-steps/s, mean torso_z={height:.3f}, diverged={diverged}/{B}")


if __name__ == "__main__":
    main()
