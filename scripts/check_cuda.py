"""Check the engine and the envs on a CUDA device against the CPU: the same step, the same answer.

    python scripts/check_cuda.py                      # every shipped model, both methods, then every env
    python scripts/check_cuda.py --models ant.xml --skip-envs --out /tmp/check_cuda.md
    python scripts/check_cuda.py --strategy kernel --methods spring --skip-envs --skip-render   # the GPU kernel

1. **Physics.** Every model in ``envs/assets`` (URDFs as the envs translate them), spring and xpbd: ``--batch``
   envs from random joint angles within range and random rates, under random controls held for ``--steps`` env
   steps, once on the CPU and once on the GPU, both eager, both float64. The GPU's state must equal the CPU's to
   ``--tol`` (relative to the state's scale): the two differ only in the order of floating-point sums, so
   short-horizon differences of 1e-12-1e-9 are rounding, and anything near 1e-3 is a bug. Contact-rich models are
   chaotic, so the horizon is short. The same run in float32 on the GPU is compared with float32 on the CPU, both
   against the CPU in float64: the GPU must not be less accurate than the CPU at the precision the envs train in.
   ``--strategy`` runs the GPU's rollouts through ``torchsim.Stepper(sys, strategy)`` instead (``kernel``: the
   whole step as one generated CUDA kernel), against the same eager CPU reference.
2. **Envs.** Every env of ``torchsim.envs`` on the GPU: TorchRL's ``check_env_specs``, every output tensor on the
   GPU, a random rollout with no diverged env.
3. **Cameras.** ``torchsim.render`` of ``--render-batch`` random states of the ant, reacher and grasp scenes, float32,
   tiled and ``compile=True``, on both devices: the GPU's depth must equal the CPU's to 1e-4 relative on at least
   99.9% of pixels and its segmentation on at least 99.9% (float rounding moves a few edge pixels' nearest geom).

Exits non-zero if any check fails. Needs a CUDA device (``--device``).
"""

import argparse
import pathlib
import sys
import time

import mujoco
import numpy as np
import torch

import torchsim
import torchsim.envs
from torchsim.envs.base import ASSETS_DIR
from torchsim.io_urdf import urdf_to_mjcf

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))  # bench_render.py's cameras
from _views import VIEW  # noqa: E402


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--models", nargs="*", help="asset file names (default: every shipped model)")
    p.add_argument("--methods", nargs="+", default=["spring", "xpbd"], choices=["spring", "xpbd"])
    p.add_argument("--strategy", default=None, help="the GPU's rollouts through torchsim.Stepper(sys, strategy)")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--steps", type=int, default=20, help="env steps per physics comparison")
    p.add_argument("--tol", type=float, default=1e-8, help="float64: max |gpu - cpu| / scale")
    p.add_argument("--env-batch", type=int, default=256)
    p.add_argument("--env-steps", type=int, default=100)
    p.add_argument("--skip-envs", action="store_true")
    p.add_argument("--skip-physics", action="store_true")
    p.add_argument("--skip-render", action="store_true")
    p.add_argument("--render-batch", type=int, default=64)
    p.add_argument("--out", help="also write the tables (markdown) here")
    return p.parse_args()


def random_inputs(m: mujoco.MjModel, batch: int, steps: int, rng: np.random.Generator):
    """Start angles within range (free joints and balls left at qpos0), rates ~ N(0, 0.5), and per-step controls
    uniform in the control range: ``q (B, nq)``, ``qd (B, nv)``, ``ctrl (steps, B, nu)``."""
    q = np.tile(m.qpos0, (batch, 1))
    for j in range(m.njnt):
        if m.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            lo, hi = m.jnt_range[j] if m.jnt_limited[j] else (-0.5, 0.5)
            q[:, m.jnt_qposadr[j]] = rng.uniform(lo, hi, batch)
    qd = 0.5 * rng.standard_normal((batch, m.nv))
    lo, hi = m.actuator_ctrlrange.T if m.nu else (np.zeros(0), np.zeros(0))
    ctrl = rng.uniform(lo, hi, (steps, batch, m.nu))
    return q, qd, ctrl


def rollout(xml: str, method: str, device: str, dtype: torch.dtype, q, qd, ctrl, strategy=None) -> torchsim.State:
    sys_ = torchsim.load_mjcf(xml, method=method, dtype=dtype, device=device)
    step = torchsim.Stepper(sys_, strategy) if strategy else lambda s, c: torchsim.step(sys_, s, c)
    as_tensor = lambda x: torch.as_tensor(x, dtype=dtype, device=device)  # noqa: E731
    with torch.no_grad():
        state = torchsim.init(sys_, as_tensor(q), as_tensor(qd))
        for c in as_tensor(ctrl):
            state = step(state, c)
    if strategy and step.strategy != strategy:  # a fallback would check another strategy than the one asked for
        raise RuntimeError(f"the {strategy} strategy fell back to {step.strategy}")
    return state


def state_error(state: torchsim.State, ref: torchsim.State) -> float:
    """Max over q, qd of ``max |x - x_ref| / max(1, max |x_ref|)``, with the state moved to the reference's device
    and dtype; inf where either is non-finite."""
    worst = 0.0
    for x, x_ref in ((state.q, ref.q), (state.qd, ref.qd)):
        x = x.to(device=x_ref.device, dtype=x_ref.dtype)
        if not (torch.isfinite(x).all() and torch.isfinite(x_ref).all()):
            return float("inf")
        worst = max(worst, float((x - x_ref).abs().max() / x_ref.abs().max().clamp_min(1.0)))
    return worst


def check_physics(args, device: str) -> tuple[list[str], bool]:
    names = args.models or sorted(p.name for p in ASSETS_DIR.iterdir() if p.suffix in (".xml", ".urdf"))
    rows = ["| model | method | f64 GPU vs CPU | f32 CPU vs f64 CPU | f32 GPU vs f64 CPU | diverged (CPU/GPU) | ok |",
            "|---|---|---:|---:|---:|---|---|"]
    all_ok = True
    rng = np.random.default_rng(0)
    for name in names:
        path = ASSETS_DIR / name
        xml = urdf_to_mjcf(path) if path.suffix == ".urdf" else path.read_text()
        m = mujoco.MjModel.from_xml_string(xml)
        for method in args.methods:
            t0 = time.perf_counter()
            q, qd, ctrl = random_inputs(m, args.batch, args.steps, rng)
            ref = rollout(xml, method, "cpu", torch.float64, q, qd, ctrl)
            gpu = rollout(xml, method, device, torch.float64, q, qd, ctrl, args.strategy)
            cpu32 = rollout(xml, method, "cpu", torch.float32, q, qd, ctrl)
            gpu32 = rollout(xml, method, device, torch.float32, q, qd, ctrl, args.strategy)
            err64, err32_cpu, err32_gpu = state_error(gpu, ref), state_error(cpu32, ref), state_error(gpu32, ref)
            same_flags = bool((gpu.diverged.cpu() == ref.diverged).all())
            # float32 on the GPU may differ from float32 on the CPU by rounding, not by a step's worth of physics
            ok = err64 <= args.tol and same_flags and err32_gpu <= max(10 * err32_cpu, 1e-4)
            all_ok &= ok
            flags = f"{int(ref.diverged.sum())}/{int(gpu.diverged.sum())}"
            rows.append(f"| {name} | {method} | {err64:.1e} | {err32_cpu:.1e} | {err32_gpu:.1e} | {flags} | "
                        f"{'yes' if ok else 'NO'} |")
            print(f"{name:28s} {method:6s} f64 gpu-cpu {err64:.1e}  f32 cpu {err32_cpu:.1e}  f32 gpu {err32_gpu:.1e}"
                  f"  diverged {flags}  {'ok' if ok else 'FAIL'}  ({time.perf_counter() - t0:.1f} s)", flush=True)
    return rows, all_ok


def sync(device: str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def check_envs(args, device: str) -> tuple[list[str], bool]:
    from torchrl.envs.utils import check_env_specs

    rows = ["| env | check_env_specs | outputs on GPU | non-finite envs | eager env-steps/s | ok |",
            "|---|---|---|---:|---:|---|"]
    all_ok = True
    for name in torchsim.envs.list("physics"):
        t0 = time.perf_counter()
        try:
            env = torchsim.envs.make(name, num_envs=args.env_batch, device=device)
            check_env_specs(env)
            specs_ok = "yes"
        except Exception as exc:  # the row says what failed; the other envs still run
            rows.append(f"| {name} | {type(exc).__name__}: {str(exc)[:80]} | | | | NO |")
            print(f"{name:26s} FAIL {type(exc).__name__}: {exc}", flush=True)
            all_ok = False
            continue
        with torch.no_grad():
            env.rollout(3)  # warm-up
            sync(device)
            start = time.perf_counter()
            td = env.rollout(args.env_steps, break_when_any_done=False)
            sync(device)
            rate = args.env_batch * args.env_steps / (time.perf_counter() - start)
        on_device = all(t.device.type == torch.device(device).type for t in td.values(True, True))
        finite = torch.isfinite(td["next", "observation"]).all(-1) & torch.isfinite(td["next", "reward"]).all(-1)
        diverged = int((~finite).any(-1).sum())  # envs with any non-finite observation or reward
        ok = on_device and diverged == 0
        all_ok &= ok
        rows.append(f"| {name} | {specs_ok} | {'yes' if on_device else 'NO'} | {diverged} | {rate:,.0f} | "
                    f"{'yes' if ok else 'NO'} |")
        print(f"{name:26s} specs ok, on device {on_device}, diverged {diverged}, {rate:,.0f} env-steps/s eager "
              f"({time.perf_counter() - t0:.1f} s)", flush=True)
    return rows, all_ok


def check_render(args, device: str) -> tuple[list[str], bool]:
    from torchsim.render import Camera, Scene, render

    rows = ["| scene | batch | depth equal (1e-4 rel) | segmentation equal | ok |", "|---|---:|---:|---:|---|"]
    all_ok = True
    views = {name: VIEW[name] for name in ("ant", "reacher", "grasp")}
    rng = np.random.default_rng(1)
    for name, (eye, target) in views.items():
        xml = torchsim.envs.asset_path(f"{name}.xml").read_text()
        m = mujoco.MjModel.from_xml_string(xml)
        q, qd, _ = random_inputs(m, args.render_batch, 1, rng)
        images = []
        for dev in ("cpu", device):
            sys_ = torchsim.load_mjcf(xml, device=dev)
            state = torchsim.init(sys_, torch.as_tensor(q, dtype=torch.float32, device=dev),
                                  torch.as_tensor(qd, dtype=torch.float32, device=dev))
            cam = Camera.look_at(eye, target, fovy=float(m.vis.global_.fovy))
            images.append(render(Scene.build(m, sys_), state, cam, 64, 64, compile=True))
        cpu, gpu = images
        close = (gpu.depth.cpu() - cpu.depth).abs() <= 1e-4 * cpu.depth.abs().clamp_min(1.0)
        depth_eq = float(close.double().mean())
        seg_eq = float((gpu.segmentation.cpu() == cpu.segmentation).double().mean())
        ok = depth_eq >= 0.999 and seg_eq >= 0.999
        all_ok &= ok
        rows.append(f"| {name} | {args.render_batch} | {depth_eq:.5f} | {seg_eq:.5f} | {'yes' if ok else 'NO'} |")
        print(f"render {name:10s} depth equal {depth_eq:.5f}  segmentation equal {seg_eq:.5f}  "
              f"{'ok' if ok else 'FAIL'}", flush=True)
    return rows, all_ok


def main():
    args = parse_args()
    device = args.device
    if torch.device(device).type == "cuda" and not torch.cuda.is_available():
        sys.exit("check_cuda: no CUDA device visible to torch")
    name = torch.cuda.get_device_name(device) if torch.device(device).type == "cuda" else device
    header = f"Device: {name}; torch {torch.__version__}; mujoco {mujoco.__version__}"
    print(header, flush=True)
    text, ok = [header, ""], True
    if not args.skip_physics:
        rows, ok = check_physics(args, device)
        how = f"the {args.strategy} strategy on the GPU" if args.strategy else "eager"
        text += [f"Physics: batch {args.batch}, {args.steps} env steps, {how}", "", *rows, ""]
    if not args.skip_envs:
        env_rows, env_ok = check_envs(args, device)
        ok &= env_ok
        text += [f"Envs: batch {args.env_batch}, {args.env_steps} steps of random actions, eager", "", *env_rows, ""]
    if not args.skip_render:
        render_rows, render_ok = check_render(args, device)
        ok &= render_ok
        text += ["Cameras: 64x64 depth and segmentation, float32, GPU against CPU", "", *render_rows, ""]
    print("\n".join(text))
    if args.out:
        pathlib.Path(args.out).write_text("\n".join(text) + "\n")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
