"""Benchmark torchsim's physics step (eager and torch.compile) against MuJoCo C (``mujoco.rollout``).

Throughput is physics steps per second summed over the batch (batch * steps / seconds); one step advances
``sys.timestep`` (0.01 s for the Ant) with ``sys.substeps`` substeps. Warm-up is excluded; for torch.compile the
first call (tracing + compiling + one step) is reported separately as the compile time. Every measurement is
repeated ``--repeats`` times and the median is reported. MuJoCo runs the same model, batch and number of steps
per rollout through ``mujoco.rollout`` with one thread and with one thread per CPU core.

Speed claims come with accuracy: at the end each method is run in float64 (batch 1, eager, zero control) from
the model's first keyframe next to MuJoCo, and the torso-height difference is printed at 0.5 s and 2 s.

    python benchmarks/bench_physics.py                                  # full default run
    python benchmarks/bench_physics.py --methods xpbd --batches 1 64 --repeats 1 --out /tmp/bench.md
    python benchmarks/bench_physics.py --no-compile --steps 5          # eager + MuJoCo only

``--steps`` defaults to "auto": per method, batch and mode (eager / compiled) the number of timed steps is chosen
from the warm-up step time so that one measurement takes about ``--min-time`` seconds (at least 1 step, at most
``--max-steps``). MuJoCo then uses the compiled (else the eager) step count per rollout call, raised so that one call
does at least ``--mujoco-min-env-steps`` env-steps, and repeats the call until ``--min-time`` has elapsed, so that its
timing is not dominated by call overhead at small batch.
"""

import argparse
import datetime
import math
import os
import pathlib
import platform
import statistics
import subprocess
import sys as _sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", nargs="+", default=["xpbd", "spring"], choices=["xpbd", "spring"])
    p.add_argument("--batches", nargs="+", type=int, default=[1, 64, 1024, 4096])
    p.add_argument("--steps", type=int, default=None,
                   help="timed steps per measurement (default: auto, see --min-time / --max-steps)")
    p.add_argument("--min-time", type=float, default=1.0, help="auto steps: target seconds per measurement")
    p.add_argument("--max-steps", type=int, default=200, help="auto steps: upper bound")
    p.add_argument("--mujoco-min-env-steps", type=int, default=1000,
                   help="MuJoCo: raise the steps per rollout call so that batch * steps >= this (call overhead)")
    p.add_argument("--repeats", type=int, default=3, help="measurements per number reported (median)")
    p.add_argument("--no-compile", action="store_true", help="skip torch.compile")
    p.add_argument("--no-eager", action="store_true", help="skip eager mode")
    p.add_argument("--no-mujoco", action="store_true", help="skip the MuJoCo reference timings")
    p.add_argument("--no-accuracy", action="store_true", help="skip the float64 accuracy check against MuJoCo")
    p.add_argument("--compile-scope", choices=["step", "stepper"], default="stepper",
                   help="'stepper' (default): torchsim.Stepper(sys, --strategy), the engine's compiled step; "
                        "'step': torch.compile(torchsim.step) as a whole (loop nests; slower on CPU)")
    p.add_argument("--strategy", default="auto", help="torchsim.Stepper strategy: auto, kernel, rows, loop or calls")
    p.add_argument("--simdlen", type=int, default=None,
                   help="inductor's cpp.simdlen: 256 makes AVX2 code on an AVX-512 machine, 1 scalar code "
                        "(default: the machine's widest)")
    p.add_argument("--no-cpp-wrapper", action="store_true",
                   help="Inductor's Python wrapper around the kernels (torchsim.Stepper uses its C++ wrapper)")
    p.add_argument("--part-size", type=int, default=512,
                   help="torchsim.Stepper(part_size=...), strategies loop and calls: CPU batches run as parts of at "
                        "most this many envs on one thread per core (0: one part)")
    p.add_argument("--compile-style", choices=["closure", "arg"], default="closure",
                   help="'closure': compile lambda s, c: step(sys, s, c); 'arg': compile step itself, sys as argument")
    p.add_argument("--keep-inductor-cache", action="store_true",
                   help="use the default inductor cache (compile times may then be warm); default: a fresh "
                        "temporary cache directory so compile times are cold")
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--device", default="cpu", help="cpu or cuda[:i]")
    p.add_argument("--threads", type=int, default=None,
                   help="torch intra-op threads (default: torch's default, one per core). On a machine shared with "
                        "other busy processes 1 can be much faster than the default (OpenMP threads wait on each "
                        "other at every op)")
    p.add_argument("--model", default=str(ROOT / "envs" / "assets" / "ant.xml"))
    p.add_argument("--contact-model", default="impulse", choices=["impulse", "soft", "articulated"],
                   help="torchsim.load_mjcf's contact_model (spring method)")
    p.add_argument("--accuracy-seconds", type=float, default=2.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="write the results as markdown to this path")
    return p.parse_args(argv)


ARGS = parse_args()
if not ARGS.keep_inductor_cache and "TORCHINDUCTOR_CACHE_DIR" not in os.environ:
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_physics_inductor_")

import mujoco  # noqa: E402
import mujoco.rollout  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import torchsim  # noqa: E402
import torchsim.pipeline  # noqa: E402
from _timing import allow_recompiles  # noqa: E402


def log(msg=""):
    print(msg, flush=True)


# ----------------------------------------------------------------------------------------------- machine info
def cpu_model() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_info() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.split("\n")
        dirty = [line[3:] for line in dirty if line.strip()]
        return f"{rev}" + (f" (dirty: {', '.join(dirty)})" if dirty else " (clean)")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine_info(device: torch.device, dtype: torch.dtype) -> dict:
    info = {
        "date": datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
        "git": git_info(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "mujoco": mujoco.__version__,
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "compile": f"scope={ARGS.compile_scope}" + (f" style={ARGS.compile_style}" if ARGS.compile_scope == "step" else
                                                     f" strategy={ARGS.strategy}")
                   + (f" simdlen={ARGS.simdlen}" if ARGS.simdlen else " SIMD"),
        "device": str(device) + (f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""),
        "dtype": str(dtype).replace("torch.", ""),
        "loadavg_start": " ".join(f"{x:.2f}" for x in os.getloadavg()),
    }
    return info


# ----------------------------------------------------------------------------------------------- inputs
def home_qpos(m: mujoco.MjModel) -> np.ndarray:
    """The model's first keyframe qpos if it has one, else qpos0."""
    return np.array(m.key_qpos[0] if m.nkey > 0 else m.qpos0, dtype=np.float64)


def quat_slices(m: mujoco.MjModel) -> list:
    out = []
    for j in range(m.njnt):
        adr = int(m.jnt_qposadr[j])
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out.append(slice(adr + 3, adr + 7))
        elif m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            out.append(slice(adr, adr + 4))
    return out


def make_inputs(m: mujoco.MjModel, batch: int, rng: np.random.Generator):
    """Keyframe tiled over the batch with small perturbations, and one random control per env in ctrlrange."""
    q = np.tile(home_qpos(m), (batch, 1))
    q += rng.uniform(-0.01, 0.01, q.shape)
    for s in quat_slices(m):
        q[:, s] /= np.linalg.norm(q[:, s], axis=1, keepdims=True)
    qd = rng.normal(0.0, 0.01, (batch, m.nv))
    lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -1.0)
    hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], 1.0)
    ctrl = rng.uniform(lo, hi, (batch, m.nu))
    return q, qd, ctrl


# ----------------------------------------------------------------------------------------------- timing helpers
def sync(device: torch.device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device) -> float:
    sync(device)
    t0 = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - t0


def auto_steps(step_time: float) -> int:
    if ARGS.steps is not None:
        return ARGS.steps
    return int(min(ARGS.max_steps, max(1, math.ceil(ARGS.min_time / max(step_time, 1e-9)))))


def bench_torchsim(step_fn, state, ctrl, batch: int, device, label: str, graphs=None) -> dict:
    """Warm up (two calls after the compile call of compiled functions), then time repeats; ``graphs()``, if
    given, counts compiled graphs, to report recompilations inside the timed repeats."""
    holder = {"s": state}

    def one():
        holder["s"] = step_fn(holder["s"], ctrl)

    one()
    t_step = timed(one, device)
    steps = auto_steps(t_step)

    def run():
        for _ in range(steps):
            holder["s"] = step_fn(holder["s"], ctrl)

    rates = []
    graphs_before = graphs() if graphs else 0
    for r in range(ARGS.repeats):
        dt = timed(run, device)
        rates.append(batch * steps / dt)
        log(f"    {label}: repeat {r + 1}/{ARGS.repeats}: {steps} steps in {dt:.3f} s -> {rates[-1]:,.0f} steps/s")
    diverged = int(holder["s"].diverged.sum().item())
    return {"rate": statistics.median(rates), "steps": steps, "repeats": len(rates), "diverged": diverged,
            "warm_step_s": t_step, "recompiles": (graphs() - graphs_before) if graphs else 0}


def mujoco_rollout_rate(m, datas, init_state, control, nstep, out) -> float:
    """Median steps/s over repeats; each repeat calls rollout until --min-time elapsed."""
    batch = init_state.shape[0]
    rates = []
    for _ in range(ARGS.repeats):
        calls, t0 = 0, time.perf_counter()
        while True:
            mujoco.rollout.rollout(m, datas, init_state, control, nstep=nstep, state=out)
            calls += 1
            dt = time.perf_counter() - t0
            if dt >= ARGS.min_time:
                break
        rates.append(batch * nstep * calls / dt)
    return statistics.median(rates)


def bench_mujoco(m, q, qd, ctrl, nstep: int) -> dict:
    batch = q.shape[0]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m, spec)
    d = mujoco.MjData(m)
    init_state = np.empty((batch, nstate))
    for b in range(batch):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = q[b]
        d.qvel[:] = qd[b]
        mujoco.mj_getState(m, d, init_state[b], spec)
    control = np.ascontiguousarray(ctrl[:, None, :])  # (batch, 1, nu): fixed over the steps, like torchsim's
    out = np.empty((batch, nstep, nstate))
    nthreads = os.cpu_count() or 1
    res = {"nstep": nstep, "threads": nthreads}
    mujoco.rollout.rollout(m, d, init_state, control, nstep=nstep, state=out)  # warm-up
    res["rate1"] = mujoco_rollout_rate(m, d, init_state, control, nstep, out)
    datas = [mujoco.MjData(m) for _ in range(nthreads)]
    mujoco.rollout.rollout(m, datas, init_state, control, nstep=nstep, state=out)  # warm-up
    res["rateN"] = mujoco_rollout_rate(m, datas, init_state, control, nstep, out)
    return res


# ----------------------------------------------------------------------------------------------- torch.compile
def configure_dynamo():
    allow_recompiles()
    if ARGS.simdlen:
        torch._inductor.config.cpp.simdlen = ARGS.simdlen


def warm_engine(system, device, dtype):
    """One eager step at batch 1 so that lazily built module-level tables (e.g. ``torchsim.spatial._CACHE``, keyed by
    dtype and device) exist before tracing; otherwise the traced code mutates them and the first compiled call is
    followed by a guard failure and a second full compile."""
    with torch.no_grad():
        state = torchsim.init(system, system.q0.to(device=device, dtype=dtype)[None],
                              torch.zeros(1, system.nv, device=device, dtype=dtype))
        torchsim.step(system, state, torch.zeros(1, system.nu, device=device, dtype=dtype))


def make_compiled(system):
    """Return (step_fn(state, ctrl), restore()) for the chosen compile scope and style."""
    if ARGS.compile_scope == "stepper":
        torch._dynamo.reset()  # a fresh compile per batch size, so that its compile time is measured
        options = ({"cpp.simdlen": ARGS.simdlen} if ARGS.simdlen else {}) | (
            {"cpp_wrapper": False} if ARGS.no_cpp_wrapper else {})
        stepper = torchsim.Stepper(system, ARGS.strategy, part_size=ARGS.part_size, inductor_options=options)
        return stepper, (lambda: None)
    if ARGS.compile_style == "closure":
        fn = torch.compile(lambda s, c: torchsim.step(system, s, c), fullgraph=True, dynamic=False)
        return fn, (lambda: None)
    fn = torch.compile(torchsim.step, fullgraph=True, dynamic=False)
    return (lambda s, c: fn(system, s, c)), (lambda: None)


# ----------------------------------------------------------------------------------------------- accuracy
def accuracy(method: str, m: mujoco.MjModel) -> dict:
    """Torso height (free-joint qpos z) of torchsim (float64, batch 1, eager) vs MuJoCo; home keyframe, zero ctrl."""
    system = torchsim.load_mjcf(ARGS.model, method=method, dtype=torch.float64, contact_model=ARGS.contact_model)
    dt = float(system.timestep)
    n_total = int(round(ARGS.accuracy_seconds / dt))
    marks = sorted({int(round(0.5 / dt)), n_total})
    q0 = home_qpos(m)
    zi = 2 if m.njnt > 0 and m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE else None
    if zi is None:
        return {"error": "first joint is not a free joint; no torso height to compare"}
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    z_mj = {}
    for i in range(1, n_total + 1):
        mujoco.mj_step(m, d)
        if i in marks:
            z_mj[i] = float(d.qpos[zi])
    t0 = time.perf_counter()
    with torch.no_grad():
        state = torchsim.init(system, torch.tensor(q0)[None], torch.zeros(1, system.nv, dtype=torch.float64))
        ctrl = torch.zeros(1, system.nu, dtype=torch.float64)
        z_ts = {}
        for i in range(1, n_total + 1):
            state = torchsim.step(system, state, ctrl)
            if i in marks:
                z_ts[i] = float(state.q[0, zi])
    wall = time.perf_counter() - t0
    rows = [{"t": i * dt, "z_torchsim": z_ts[i], "z_mujoco": z_mj[i], "diff_mm": abs(z_ts[i] - z_mj[i]) * 1e3}
            for i in marks]
    return {"rows": rows, "wall_s": wall, "diverged": bool(state.diverged.any())}


# ----------------------------------------------------------------------------------------------- report
def fmt_rate(x):
    return "—" if x is None else f"{x:,.0f}"


def results_markdown(info, results, acc, total_s) -> str:
    lines = [
        "| method | batch | eager steps/s | compiled steps/s | compile time s | MuJoCo 1 thread steps/s "
        f"| MuJoCo {info['cpu_count']} threads steps/s | compiled / MuJoCo({info['cpu_count']} threads) "
        "| timed steps × repeats (eager / compiled / MuJoCo per call) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in results:
        e, c, mj = r.get("eager"), r.get("compiled"), r.get("mujoco")
        best = c["rate"] if c and "rate" in c else None
        ratio = f"{best / mj['rateN']:.3g}" if best and mj else "—"
        ctime = f"{c['compile_s']:.1f}" if c and "compile_s" in c else ("error" if c and "error" in c else "—")
        detail = " / ".join([
            f"{e['steps']}×{e['repeats']}" if e else "—",
            f"{c['steps']}×{c['repeats']}" if c and "steps" in c else "—",
            f"{mj['nstep']}" if mj else "—",
        ])
        lines.append(f"| {r['method']} | {r['batch']} | {fmt_rate(e and e['rate'])} | "
                     f"{fmt_rate(c['rate'] if c and 'rate' in c else None)} | {ctime} | "
                     f"{fmt_rate(mj and mj['rate1'])} | {fmt_rate(mj and mj['rateN'])} | {ratio} | {detail} |")
    out = ["Machine: " + ", ".join(f"{k}={v}" for k, v in info.items()), "", *lines, ""]
    errors = [(r["method"], r["batch"], r["compiled"]["error"]) for r in results
              if r.get("compiled") and "error" in r["compiled"]]
    for method, batch, err in errors:
        out += [f"torch.compile error ({method}, batch {batch}):", "", "```", err, "```", ""]
    if acc:
        out += ["Accuracy (float64, batch 1, eager, home keyframe, zero control; torso height = free-joint qpos z):",
                "", "| method | t s | z torchsim m | z MuJoCo m | abs diff mm |", "|---|---:|---:|---:|---:|"]
        for method, a in acc.items():
            if "error" in a:
                out.append(f"| {method} | — | — | — | {a['error']} |")
                continue
            for row in a["rows"]:
                out.append(f"| {method} | {row['t']:.2f} | {row['z_torchsim']:.4f} | {row['z_mujoco']:.4f} | "
                           f"{row['diff_mm']:.1f} |")
        out.append("")
    out.append(f"Total wall time: {total_s / 60:.1f} min")
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------------------------- main
def main():
    t_start = time.perf_counter()
    if ARGS.threads:
        torch.set_num_threads(ARGS.threads)
    device = torch.device(ARGS.device)
    dtype = getattr(torch, ARGS.dtype)
    configure_dynamo()
    info = machine_info(device, dtype)
    log("bench_physics: " + " ".join(_sys.argv[1:]))
    for k, v in info.items():
        log(f"  {k}: {v}")
    log(f"  inductor cache: {os.environ.get('TORCHINDUCTOR_CACHE_DIR', 'default')}")

    m = mujoco.MjModel.from_xml_path(ARGS.model)
    log(f"  model: {ARGS.model} (nq={m.nq} nv={m.nv} nu={m.nu}, key={'yes' if m.nkey else 'no'}, "
        f"MuJoCo timestep={m.opt.timestep:g})")
    results = []
    for method in ARGS.methods:
        system = torchsim.load_mjcf(ARGS.model, method=method, dtype=dtype, device=device,
                                    contact_model=ARGS.contact_model)
        log(f"\n[{method}] timestep={system.timestep:g} s, substeps={system.substeps}")
        warm_engine(system, device, dtype)
        for batch in ARGS.batches:
            rng = np.random.default_rng(ARGS.seed + batch)
            q_np, qd_np, ctrl_np = make_inputs(m, batch, rng)
            q = torch.tensor(q_np, dtype=dtype, device=device)
            qd = torch.tensor(qd_np, dtype=dtype, device=device)
            ctrl = torch.tensor(ctrl_np, dtype=dtype, device=device)
            res = {"method": method, "batch": batch}
            with torch.no_grad():
                state0 = torchsim.init(system, q, qd)
                if not ARGS.no_eager:
                    step = lambda s, c: torchsim.step(system, s, c)  # noqa: E731
                    res["eager"] = bench_torchsim(step, state0, ctrl, batch, device, f"{method} B={batch} eager")
                    log(f"  {method} batch={batch} eager: {res['eager']['rate']:,.0f} steps/s "
                        f"(median of {res['eager']['repeats']} x {res['eager']['steps']} steps, "
                        f"diverged {res['eager']['diverged']}/{batch})")
                if not ARGS.no_compile:
                    torch._dynamo.reset()
                    fn, restore = make_compiled(system)
                    try:
                        holder = {}
                        graphs = lambda: torch._dynamo.utils.counters["stats"]["unique_graphs"]  # noqa: E731
                        g0 = graphs()
                        compile_s = timed(lambda: holder.setdefault("s", fn(state0, ctrl)), device)
                        g1 = graphs()
                        log(f"  {method} batch={batch} compiled: compile (first call) {compile_s:.1f} s, "
                            f"{g1 - g0} graph(s)")
                        res["compiled"] = bench_torchsim(fn, holder["s"], ctrl, batch, device,
                                                         f"{method} B={batch} compiled", graphs)
                        res["compiled"]["compile_s"] = compile_s
                        if res["compiled"]["recompiles"]:
                            log(f"  WARNING: {res['compiled']['recompiles']} recompilation(s) during the timed "
                                "repeats; that time is included in the compiled steps/s")
                        elif graphs() != g1:
                            log(f"  note: {graphs() - g1} recompilation(s) during the warm-up calls (not timed)")
                        log(f"  {method} batch={batch} compiled: {res['compiled']['rate']:,.0f} steps/s "
                            f"(median of {res['compiled']['repeats']} x {res['compiled']['steps']} steps, "
                            f"diverged {res['compiled']['diverged']}/{batch})")
                    except Exception as exc:  # report verbatim, keep going
                        msg = f"{type(exc).__name__}: {exc}"
                        res["compiled"] = {"error": msg}
                        log(f"  {method} batch={batch} compiled: ERROR\n{msg}")
                    finally:
                        restore()
            if not ARGS.no_mujoco:
                src = res.get("compiled") if res.get("compiled") and "steps" in res["compiled"] else res.get("eager")
                nstep = src["steps"] if src else (ARGS.steps or 1)
                nstep = max(nstep, math.ceil(ARGS.mujoco_min_env_steps / batch))
                res["mujoco"] = bench_mujoco(m, q_np, qd_np, ctrl_np, nstep)
                mj = res["mujoco"]
                log(f"  MuJoCo batch={batch} nstep={nstep}: 1 thread {mj['rate1']:,.0f} steps/s, "
                    f"{mj['threads']} threads {mj['rateN']:,.0f} steps/s")
            results.append(res)

    acc = {}
    if not ARGS.no_accuracy:
        log(f"\naccuracy vs MuJoCo (float64, batch 1, eager, zero control, {ARGS.accuracy_seconds:g} s):")
        for method in ARGS.methods:
            acc[method] = a = accuracy(method, m)
            if "error" in a:
                log(f"  {method}: {a['error']}")
                continue
            for row in a["rows"]:
                log(f"  {method} t={row['t']:.2f}s: z torchsim {row['z_torchsim']:.4f} m, z MuJoCo "
                    f"{row['z_mujoco']:.4f} m, |diff| {row['diff_mm']:.1f} mm")
            log(f"  {method}: {a['wall_s']:.1f} s wall, diverged={a['diverged']}")

    info["loadavg_end"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    total = time.perf_counter() - t_start
    md = results_markdown(info, results, acc, total)
    log("\n" + md)
    if ARGS.out:
        pathlib.Path(ARGS.out).write_text(f"Command: `python benchmarks/bench_physics.py {' '.join(_sys.argv[1:])}`\n\n"
                                          + md)
        log(f"wrote {ARGS.out}")


if __name__ == "__main__":
    main()
