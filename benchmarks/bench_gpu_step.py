"""Steps/s of the step kernel on a GPU, beside MuJoCo C on the same machine's CPU cores, in one run.

    python benchmarks/bench_gpu_step.py                                   # Ant and Humanoid at 4096, 16384, 65536
    python benchmarks/bench_gpu_step.py --models ant --batches 4096 --sweep --out /tmp/bench.md

torchsim: ``torchsim.Stepper(sys, --strategy)`` on ``--device`` in ``--dtype`` (the ``kernel`` strategy on CUDA is
the whole step as one CUDA kernel, one launch a step), timed over ``--steps`` steps with the device synchronised
before and after, the median of ``--repeats``; its first call (tracing the row graphs, writing the kernel, NVRTC's
compile) is reported apart. MuJoCo C: ``mujoco.rollout`` of the same model and batch on one thread per CPU core.
``--sweep`` times each block size (envs per block of the CUDA kernel) at every batch. A
step is one env step (``sys.timestep``, ``sys.substeps`` substeps), for both.
"""

import argparse
import os
import statistics
import subprocess
import sys
import time

import mujoco
import numpy as np
import torch

import torchsim
import torchsim.envs
from _timing import emit_table, mujoco_rollout_rate, mujoco_start_states
from torchsim.io_urdf import urdf_to_mjcf

#: threads (envs) per block of the CUDA kernel: few at small batches spread the envs over more of the GPU's SMs
BLOCKS = [32, 64, 128, 256]


def parse_args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda")
    p.add_argument("--models", nargs="+", default=["ant", "humanoid"])
    p.add_argument("--batches", nargs="+", type=int, default=[4096, 16384, 65536])
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--strategy", default="kernel")
    p.add_argument("--block", type=int, default=128, help="envs (threads) per block of the CUDA kernel")
    p.add_argument("--sweep", action="store_true", help=f"time every block size of {BLOCKS} at every batch")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--mujoco-steps", type=int, default=20)
    p.add_argument("--no-mujoco", action="store_true")
    p.add_argument("--out", help="also write the table (markdown) here")
    return p.parse_args()


def load(name: str, dtype: torch.dtype, device: str):
    path = torchsim.envs.asset_path(f"{name}.xml")
    xml = urdf_to_mjcf(path) if path.suffix == ".urdf" else path.read_text()
    return torchsim.load_mjcf(xml, dtype=dtype, device=device), mujoco.MjModel.from_xml_string(xml)


def start(sys_, batch: int, seed: int = 0):
    """Starts near the model's rest pose with small random rates, and random controls in [-1, 1]."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    q = sys_.q0.cpu() + 0.02 * torch.randn(batch, sys_.nq, generator=g, dtype=sys_.dtype)
    qd = 0.1 * torch.randn(batch, sys_.nv, generator=g, dtype=sys_.dtype)
    ctrl = torch.rand(batch, sys_.nu, generator=g, dtype=sys_.dtype) * 2 - 1
    to = dict(device=sys_.device)
    return torchsim.init(sys_, q.to(**to), qd.to(**to)), ctrl.to(**to), q.double().numpy(), qd.double().numpy()


def sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def bench_stepper(stepper, state, ctrl, steps: int, repeats: int, device) -> tuple[float, float]:
    """(first call's seconds, median steps/s over ``repeats`` of ``steps`` steps)."""
    sync(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        state = stepper(state, ctrl)
        sync(device)
        first = time.perf_counter() - t0
        for _ in range(3):
            state = stepper(state, ctrl)
        rates = []
        for _ in range(repeats):
            sync(device)
            t0 = time.perf_counter()
            for _ in range(steps):
                state = stepper(state, ctrl)
            sync(device)
            rates.append(state.q.shape[0] * steps / (time.perf_counter() - t0))
    if state.diverged.any():
        print(f"  warning: {int(state.diverged.sum())} envs diverged", flush=True)
    return first, statistics.median(rates)


def main():
    args = parse_args()
    dtype = getattr(torch, args.dtype)
    device = args.device
    gpu = torch.cuda.get_device_name(device) if torch.device(device).type == "cuda" else device
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    threads = os.cpu_count() or 1
    header = (f"{gpu}; torch {torch.__version__}; {args.dtype}; strategy {args.strategy}; commit {commit or '?'}; "
              f"MuJoCo {mujoco.__version__} on {threads} CPU threads; {time.strftime('%Y-%m-%d')}")
    print(header, flush=True)
    lines = [header, "", "| model | batch | block | first call s | torchsim steps/s | MuJoCo C steps/s | "
             "ratio |", "|---|---:|---|---:|---:|---:|---:|"]
    for name in args.models:
        sys_, m = load(name, dtype, device)
        cuda = torch.device(device).type == "cuda"  # launch shapes are the CUDA kernel's; the CPU's has none
        for batch in args.batches:
            state, ctrl, q, qd = start(sys_, batch)
            mujoco_rate = float("nan")
            if not args.no_mujoco:
                controls = np.repeat(ctrl.double().cpu().numpy()[:, None], args.mujoco_steps, 1)
                mujoco_rate = mujoco_rollout_rate(m, mujoco_start_states(m, q, qd), controls, 3, threads)
            for block in (BLOCKS if args.sweep else [args.block]) if cuda else [None]:
                stepper = torchsim.Stepper(sys_, args.strategy, kernel_options=dict(block=block) if cuda else None)
                first, rate = bench_stepper(stepper, state, ctrl, args.steps, args.repeats, device)
                if stepper.strategy != args.strategy:
                    raise RuntimeError(f"the {args.strategy} strategy fell back to {stepper.strategy}")
                lines.append(f"| {name} | {batch} | {block or '-'} | {first:.1f} | {rate:,.0f} | "
                             f"{mujoco_rate:,.0f} | {rate / mujoco_rate:.1f} |")
                print(lines[-1], flush=True)
    emit_table("\n".join(lines), args.out)


if __name__ == "__main__":
    sys.exit(main())
