"""Gradients through Ant rollouts: their norm against the horizon, and the cost of
recording and back-propagating a rollout (time and memory), with and without checkpointing the steps.

    OMP_NUM_THREADS=1 python studies/grad_horizon.py horizon            # -> docs/gradients_horizon.{csv,png}
    OMP_NUM_THREADS=1 python studies/grad_horizon.py speed --batch 256 --steps 100 [--stepper compiled]
    OMP_NUM_THREADS=1 python studies/grad_horizon.py compiled --batch 256 --steps 20
    python studies/grad_horizon.py speed --device cuda --batch 256 --steps 100

``horizon``: ``--envs`` Ant starts (``q0`` plus U(-0.1, 0.1) on every coordinate, N(0, 0.1) velocities) under
uniform random controls over the ctrl range, float64, eager ``torchsim.step``. For every horizon ``H`` the scalar
``J_H = w . (q_H, qd_H)`` (a fixed random unit ``w``) is differentiated with respect to the initial velocities, the
initial coordinates, every control of the rollout and the body masses; the chart shows, per input, the median and
the largest norm over the envs against ``H``.

``speed``: one rollout of ``--steps`` steps at ``--batch`` envs, float32, eager (``--stepper compiled``: through
a ``torchsim.Stepper``, compiled, after an untimed warm-up of each kind of step): (a) forward without autograd, (b)
forward recording the graph plus ``backward`` of the summed final state, with respect to the controls and the
initial velocities, (c) the same with every step under ``torch.utils.checkpoint`` (``use_reentrant=False``): only
the states between steps are kept, and each step's intermediates are recomputed during ``backward``. Reports steps/s
(env steps, i.e. batch x steps per second) and the memory the graph holds: the bytes autograd saves for backward
(``saved_tensors_hooks``, counted once per storage), per env per step, and on CUDA the peak allocated memory.

``compiled``: whether the compiled step's gradients are the eager step's (:func:`compiled_agreement`).
"""

import argparse
import csv
import functools
import os
import resource
import time

import torch
from torch.utils.checkpoint import checkpoint

import torchsim

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ANT = os.path.join(REPO, "envs", "assets", "ant.xml")
HORIZONS = (1, 2, 5, 10, 20, 50, 100, 200)


def starts(sys, envs, gen):
    q = sys.q0.expand(envs, -1) + 0.1 * (2 * torch.rand(envs, sys.nq, generator=gen, dtype=sys.dtype) - 1)
    q[:, 3:7] = q[:, 3:7] / q[:, 3:7].norm(dim=-1, keepdim=True)
    return q, 0.1 * torch.randn(envs, sys.nv, generator=gen, dtype=sys.dtype)


def random_ctrl(sys, steps, envs, gen):
    lo, hi = sys.act_ctrl_range.unbind(-1)
    return lo + (hi - lo) * torch.rand(steps, envs, sys.nu, generator=gen, dtype=sys.dtype)


def horizon(args):
    torch.set_num_threads(1)
    sys = torchsim.load_mjcf(ANT, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    q0, qd0 = starts(sys, args.envs, gen)
    ctrl = random_ctrl(sys, max(HORIZONS), args.envs, gen)
    w = torch.randn(sys.nq + sys.nv, generator=gen, dtype=torch.float64)
    w = w / w.norm()
    q0.requires_grad_()
    qd0.requires_grad_()
    ctrl.requires_grad_()
    mass = sys.body_mass.expand(args.envs, -1).clone().requires_grad_()  # per env: per-env gradients
    model = sys.replace(body_mass=mass)
    state = torchsim.init(model, q0, qd0)
    rows = []
    start = time.perf_counter()
    for t in range(1, max(HORIZONS) + 1):
        state = torchsim.step(model, state, ctrl[t - 1])
        if t not in HORIZONS:
            continue
        objective = torch.cat((state.q, state.qd), -1) @ w
        grads = torch.autograd.grad(objective.sum(), (qd0, q0, ctrl, mass), retain_graph=t < max(HORIZONS))
        norms = {"qd0": grads[0].norm(dim=-1), "q0": grads[1].norm(dim=-1),
                 "ctrl": grads[2].transpose(0, 1).flatten(1).norm(dim=-1), "mass": grads[3].norm(dim=-1)}
        for name, n in norms.items():
            rows.append(dict(horizon=t, time_s=t * sys.timestep, input=name, median=n.median().item(),
                             max=n.max().item(), min=n.min().item()))
        print(f"H={t:4d} ({time.perf_counter() - start:6.1f} s) diverged={int(state.diverged.sum())} "
              + " ".join(f"{k}: median {v.median():.3g} max {v.max():.3g}" for k, v in norms.items()), flush=True)
    path = os.path.join(REPO, "docs", "gradients_horizon.csv")
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(path)


def plot(path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(path) as f:
        rows = list(csv.DictReader(f))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, colour in (("qd0", "C0"), ("q0", "C1"), ("ctrl", "C2"), ("mass", "C3")):
        sel = [r for r in rows if r["input"] == name]
        h = [int(r["horizon"]) for r in sel]
        ax.plot(h, [float(r["median"]) for r in sel], "o-", color=colour, label=f"d J / d {name} (median)")
        ax.plot(h, [float(r["max"]) for r in sel], "--", color=colour, alpha=0.6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("horizon H [steps of 10 ms]")
    ax.set_ylabel("gradient norm (dashed: largest of the envs)")
    ax.set_title("Ant, random controls, float64: |d (w . state_H) / d input|")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(REPO, "docs", "gradients_horizon.png"), dpi=110)


class SavedBytes:
    """Counts the bytes autograd saves for backward, once per storage."""

    def __init__(self):
        self.storages = {}

    def pack(self, t):
        if t.device.type != "meta":
            self.storages[(t.untyped_storage().data_ptr(), t.device)] = t.untyped_storage().nbytes()
        return t

    @property
    def total(self):
        return sum(self.storages.values())


def speed(args):
    device = torch.device(args.device)
    sys = torchsim.load_mjcf(ANT, dtype=torch.float32, device=device)
    gen = torch.Generator().manual_seed(0)
    q0, qd0 = (x.to(device) for x in starts(sys.to(device="cpu"), args.batch, gen))
    ctrl = random_ctrl(sys.to(device="cpu"), args.steps, args.batch, gen).to(device)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    # compiled: a torchsim.Stepper, whose steps that autograd records run compiled with their backward
    step = torchsim.Stepper(sys) if args.stepper == "compiled" else functools.partial(torchsim.step, sys)

    def one_step(x_pos, x_quat, xd_vel, xd_ang, q, qd, c):
        s = step(torchsim.State(x_pos, x_quat, xd_vel, xd_ang, q, qd, diverged, act), c)
        return s.x_pos, s.x_quat, s.xd_vel, s.xd_ang, s.q, s.qd

    def run(mode):
        c = ctrl.clone().requires_grad_(mode != "forward")
        v = qd0.clone().requires_grad_(mode != "forward")
        counter = SavedBytes()
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        base = torch.cuda.memory_allocated() if device.type == "cuda" else 0
        sync()
        start = time.perf_counter()
        with torch.autograd.graph.saved_tensors_hooks(counter.pack, lambda t: t), \
                torch.set_grad_enabled(mode != "forward"):
            state = torchsim.init(sys, q0, v)
            nonlocal diverged, act
            diverged, act = state.diverged, state.act  # the Ant's act: empty
            fields = tuple(state[:6])
            for t in range(args.steps):
                if mode == "checkpoint":
                    fields = checkpoint(one_step, *fields, c[t], use_reentrant=False)
                else:
                    fields = one_step(*fields, c[t])
        sync()
        forward = time.perf_counter() - start
        peak_fwd = torch.cuda.max_memory_allocated() - base if device.type == "cuda" else 0
        backward = 0.0
        if mode != "forward":
            start = time.perf_counter()
            (fields[4].sum() + fields[5].sum()).backward()
            sync()
            backward = time.perf_counter() - start
            assert torch.isfinite(c.grad).all() and torch.isfinite(v.grad).all()
        peak = torch.cuda.max_memory_allocated() - base if device.type == "cuda" else 0
        env_steps = args.batch * args.steps
        print(f"{mode:10s} forward {forward:7.2f} s, backward {backward:7.2f} s: "
              f"{env_steps / (forward + backward):9.0f} env steps/s; saved for backward "
              f"{counter.total / 2**20:8.1f} MiB = {counter.total / env_steps / 1024:6.1f} KiB per env per step"
              + (f"; CUDA peak {peak / 2**20:.0f} MiB (after forward {peak_fwd / 2**20:.0f} MiB), "
                 f"{peak / env_steps / 1024:.1f} KiB per env per step" if device.type == "cuda" else ""),
              flush=True)

    diverged = act = None
    print(f"Ant, batch {args.batch}, {args.steps} steps of {sys.substeps} substeps, float32, {device}, "
          f"{torch.get_num_threads()} threads, {step if args.stepper == 'compiled' else 'eager torchsim.step'}")
    warm_up = ("forward", "backward") if args.stepper == "compiled" else ("forward",)  # compiles, untimed
    for mode in warm_up + tuple(args.modes):
        run(mode)
    print(f"max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


def compiled_agreement(args):
    """Gradients of ``sum(q_H) + sum(qd_H)`` with respect to every control of an H-step rollout at ``--batch`` envs,
    float32, through a ``torchsim.Stepper`` (compiled forward and backward) and through ``torchsim.step``, against
    the float32 step's own distance from float64: the relative error over the batch (max |a - b| / max |b|), and
    the median env's (||a - b|| / ||b|| per env)."""
    sys32, sys64 = (torchsim.load_mjcf(ANT, dtype=dtype) for dtype in (torch.float32, torch.float64))
    gen = torch.Generator().manual_seed(0)
    q0, qd0 = starts(sys32, args.batch, gen)
    ctrl = random_ctrl(sys32, args.steps, args.batch, gen)
    steps = {"compiled": torchsim.Stepper(sys32), "eager32": functools.partial(torchsim.step, sys32),
             "eager64": functools.partial(torchsim.step, sys64)}

    def ctrl_grad(name, horizon):
        dtype = torch.float64 if name == "eager64" else torch.float32
        c = ctrl[:horizon].to(dtype).requires_grad_()
        state = torchsim.init(sys64 if name == "eager64" else sys32, q0.to(dtype), qd0.to(dtype))
        for t in range(horizon):
            state = steps[name](state, c[t])
        return torch.autograd.grad(state.q.sum() + state.qd.sum(), c)[0].double().transpose(0, 1).flatten(1)

    def errors(got, want):
        per_env = (got - want).norm(dim=1) / want.norm(dim=1)
        return f"{((got - want).abs().max() / want.abs().max()).item():.1e} / {per_env.median().item():.1e}"

    print(f"Ant, batch {args.batch}; relative error of d J / d controls, over the batch / the median env")
    for horizon in (h for h in HORIZONS if h <= args.steps):
        grads = {name: ctrl_grad(name, horizon) for name in steps}
        print(f"H = {horizon:3d}: compiled vs eager (float32) {errors(grads['compiled'], grads['eager32'])}; "
              f"eager float32 vs float64 {errors(grads['eager32'], grads['eager64'])}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("horizon", "speed", "compiled", "replot"))
    parser.add_argument("--envs", type=int, default=8)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--modes", nargs="+", default=["forward", "backward", "checkpoint"],
                        choices=["forward", "backward", "checkpoint"])
    parser.add_argument("--stepper", choices=["eager", "compiled"], default="eager",
                        help="speed: torchsim.step, or a torchsim.Stepper (compiled forward and backward)")
    args = parser.parse_args()
    if args.what == "horizon":
        horizon(args)
    elif args.what == "speed":
        speed(args)
    elif args.what == "compiled":
        compiled_agreement(args)
    else:
        plot(os.path.join(REPO, "docs", "gradients_horizon.csv"))


if __name__ == "__main__":
    main()
