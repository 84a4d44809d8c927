"""What each env's scene costs per env step: model size, contact pairs (vs all pairs), ops and bytes per substep.

    python studies/scene_cost.py                      # all envs, markdown table on stdout
    python studies/scene_cost.py --rates docs/bench_envs_4096.md --out docs/scene_cost.md

Counts come from one eager physics substep at batch 1 under a dispatch-mode counter: every aten op is counted,
and the bytes it writes (output tensor sizes) plus reads (input tensor sizes) give the memory traffic an unfused
execution moves per env. Floating-point work is counted as one operation per output element of elementwise ops
and ``2 * k`` per output element of reductions and products over ``k`` terms (a rough count, good to ~2x). A
fused compiled step moves less than the unfused count; the "roofline fraction" divides the traffic implied by a
measured compiled rate (``--rates``: a bench_envs.py markdown table) by this machine's copy bandwidth measured
here, so it is an upper bound on how close the compiled step runs to memory speed.
"""

import argparse
import itertools
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

import torchsim
import torchsim.envs
from torchsim.kinematics import with_world
from torchsim.lanes import to_lanes
from torchsim.methods import METHODS

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))  # the benchmarks' table helper
from _timing import emit_table  # noqa: E402

VIEW_OPS = {"view", "_unsafe_view", "expand", "select", "slice", "unsqueeze", "squeeze", "permute", "transpose",
            "t", "as_strided", "unbind", "split", "alias", "detach", "reshape", "flatten", "unflatten"}
REDUCTIONS = {"sum", "mean", "amax", "amin", "all", "any", "linalg_vector_norm", "norm"}
PRODUCTS = {"mm", "bmm", "matmul"}


class CostCounter(TorchDispatchMode):
    """Counts aten ops, the bytes they read and write, and a rough flop count."""

    def __init__(self):
        super().__init__()
        self.ops = self.bytes = self.flops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__.rstrip("_")
        if name in VIEW_OPS:
            return out
        ins = [a for a in itertools.chain(args, (kwargs or {}).values()) if isinstance(a, torch.Tensor)]
        outs = [o for o in (out if isinstance(out, (tuple, list)) else [out]) if isinstance(o, torch.Tensor)]
        self.ops += 1
        self.bytes += sum(t.numel() * t.element_size() for t in ins + outs)
        n_out = sum(o.numel() for o in outs)
        if name in PRODUCTS and len(ins) >= 2:
            self.flops += 2 * n_out * ins[0].shape[-1]
        elif name in REDUCTIONS and ins:
            self.flops += ins[0].numel()
        else:
            self.flops += n_out
        return out


def substep_cost(env) -> CostCounter:
    sys = env.sys
    state = env.state
    bodies = with_world(*(to_lanes(x[:1], 1) for x in state[:4]))
    ctrl = torch.zeros(sys.nu, 1, dtype=sys.dtype)
    h = sys.substep_timestep
    terms = METHODS[sys.method].step_terms(sys, bodies, to_lanes(state.q[:1]), h)  # once per step, not counted
    counter = CostCounter()
    with counter:
        METHODS[sys.method].substep(sys, bodies, ctrl, terms, h)
    return counter


def copy_bandwidth(nbytes: int = 1 << 28, repeats: int = 5) -> float:
    """Bytes/s of a large tensor copy (read + write), the machine's practical memory bandwidth."""
    src = torch.ones(nbytes // 4)
    dst = torch.empty_like(src)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        dst.copy_(src)
        times.append(time.perf_counter() - start)
    return 2 * nbytes / min(times)


def read_rates(path) -> dict:
    """{env: compiled env-steps/s} from the largest batch of a bench_envs.py markdown table."""
    rates = {}
    for line in open(path):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 4 and cells[1].isdigit():
            if cells[0] not in rates or int(cells[1]) >= rates[cells[0]][0]:
                rates[cells[0]] = (int(cells[1]), float(cells[3].replace(",", "")))
    return {env: rate for env, (_, rate) in rates.items()}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=torchsim.envs.list("physics"), choices=torchsim.envs.list("physics"))
    p.add_argument("--rates", default=None, help="bench_envs.py markdown table with compiled env-steps/s")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    torch.set_num_threads(1)
    rates = read_rates(args.rates) if args.rates else {}
    bandwidth = copy_bandwidth() if rates else None
    header = ("| env | bodies | joints | dofs | actuators | contact pairs (all geom pairs) | substeps per env step | "
              "ops per substep | MB per env step (unfused) | Mflop per env step | roofline fraction |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for name in args.envs:
        env = torchsim.envs.make(name)
        sys, m = env.sys, env.mj_model
        cost = substep_cost(env)
        per_step = env.frame_skip * sys.substeps
        geoms = m.ngeom
        traffic = cost.bytes * per_step
        fraction = f"{rates[name] * traffic / bandwidth:.2g}" if name in rates else "-"
        lines.append(f"| {name} | {sys.num_bodies} | {sys.jnt_child.shape[0]} | {sys.dof_flat.shape[0]} | {sys.nu} | "
                     f"{sys.num_contact_pairs} ({geoms * (geoms - 1) // 2}) | {per_step} | {cost.ops} | "
                     f"{traffic / 1e6:.2f} | {cost.flops * per_step / 1e6:.2f} | {fraction} |")
        print(lines[-1], flush=True)
    table = "\n".join(lines)
    if bandwidth:
        table += f"\n\nCopy bandwidth measured here: {bandwidth / 1e9:.1f} GB/s (1 thread)."
    emit_table(table, args.out)


if __name__ == "__main__":
    main()
