"""Third-party model check: every standalone environment MJCF in gymnasium's, Brax's and
dm_control's published wheels, loaded by MuJoCo and by torchsim, and each loaded one rolled out passively.

The wheels come from the package registry (``pip download --no-deps``) into a cache directory and are unzipped there;
a second run reuses them. Nothing is vendored into the repository.

Model set (the environment models users run): the ``*.xml`` files directly in
  gymnasium ``gymnasium/envs/mujoco/assets/``, brax ``brax/envs/assets/``, dm_control ``dm_control/suite/``
(not ``dm_control/suite/common/*``, which are include fragments). dm_control's ``lqr.xml`` (no bodies) and
``swimmer.xml`` (3 links) are templates its tasks extend in code; they are checked as shipped.

For each model: MuJoCo's compile (``torchsim.io_mjcf.mujoco_model``, the model torchsim is built from), then
``torchsim.load_mjcf`` -> LOAD, REFUSE (the
``UnsupportedMJCFError`` message) or CRASH (any other exception: an engine bug, reported with its type). For each
loaded model, a passive rollout (zero controls, float64) from ``qpos0`` with start velocities ~ N(0, 0.1) (seed 0)
for 0.5 s: torchsim (batch 1, eager ``torchsim.step``, the loader's default substeps) and MuJoCo at the model's
timestep and at timestep/4. Errors are RMS over time and qpos coordinates (hinge differences wrapped to (-pi, pi],
quaternions up to sign): ``ts``: torchsim vs MuJoCo dt/4; ``mj``: MuJoCo dt vs MuJoCo dt/4 (MuJoCo's own timestep
sensitivity). Verdict: PASS if ts <= max(k * mj, 1e-3), k = 2 where MuJoCo's rollout had no contact, k = 5 where it
had any (``d.ncon > 0`` at some step); a diverged torchsim rollout is a MISS. A torchsim rollout that exceeds
``--budget`` seconds is cut there and compared over the steps it ran (the steps column says so). A model with contacts
is rolled out again on each of ``AGAIN``'s contact models (``contact_model="soft"``, ``"articulated"``), except beyond
the loader's dense-solve warning (``geoms.SOFT_CONTACT_POINTS_WARN`` contact points: SKIP), where a single step can
outlast any budget.

    OMP_NUM_THREADS=1 python studies/check_third_party.py                 # all models, table on stdout
    OMP_NUM_THREADS=1 python studies/check_third_party.py --write-docs    # and into docs/models.md
    python studies/check_third_party.py --models ant cartpole --cache /tmp/tp_cache
"""

import argparse
import collections
import platform
import re
import subprocess
import sys as _sys
import time
import warnings
import zipfile
from datetime import datetime, timezone
from pathlib import Path

import mujoco
import numpy as np
import torch

import torchsim
from torchsim.io_mjcf.geoms import SOFT_CONTACT_POINTS_WARN
from _docs import replace_section

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs" / "models.md"
SECTION = "## Locomotion models of gymnasium, Brax and dm_control"
# distribution -> (default version, model directory inside the wheel)
PACKAGES = {
    "gymnasium": ("1.4.0", "gymnasium/envs/mujoco/assets"),
    "brax": ("0.14.2", "brax/envs/assets"),
    "dm_control": ("1.0.50", "dm_control/suite"),
}
TEMPLATES = {("dm_control", "lqr"), ("dm_control", "swimmer")}  # extended in code by their tasks
HORIZON, VEL_STD, SEED = 0.5, 0.1, 0
AGAIN = ("soft", "articulated")  # the contact models a model with contacts is rolled out again on
F64 = torch.float64


def fetch(cache: Path, dist: str, version: str) -> Path:
    """The unpacked wheel of ``dist==version`` under ``cache`` (downloaded and unzipped on first use)."""
    wheels = sorted(cache.glob(f"{dist}-{version}-*.whl"))
    if not wheels:
        cache.mkdir(parents=True, exist_ok=True)
        subprocess.run([_sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:", "-q",
                        f"{dist}=={version}", "-d", str(cache)], check=True)
        wheels = sorted(cache.glob(f"{dist}-{version}-*.whl"))
    target = cache / wheels[0].name.removesuffix(".whl")
    if not (target / ".unpacked").exists():
        with zipfile.ZipFile(wheels[0]) as z:
            z.extractall(target)
        (target / ".unpacked").touch()
    return target


def model_paths(cache: Path, versions: dict) -> list[tuple[str, Path]]:
    """(source, path) of every model by the rule in the module docstring."""
    out = []
    for dist, (_, sub) in PACKAGES.items():
        out += [(dist, p) for p in sorted((fetch(cache, dist, versions[dist]) / sub).glob("*.xml"))]
    return out


def load(path: Path, **options):
    """(status, sys or None, detail): LOAD (detail: the loader's warnings, what it ignored), REFUSE
    (UnsupportedMJCFError) or CRASH (anything else). ``options``: ``torchsim.load_mjcf``'s."""
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sys = torchsim.load_mjcf(str(path), dtype=F64, **options)
        return "LOAD", sys, "; ".join(dict.fromkeys(f"warns: {shorten(str(w.message))}" for w in caught))
    except torchsim.UnsupportedMJCFError as e:
        return "REFUSE", None, str(e)
    except Exception as e:  # a bug to report, not to hide
        return "CRASH", None, f"{type(e).__name__}: {e}"


def shorten(text: str, limit: int = 160) -> str:
    """``text`` cut to ``limit`` characters, so that a table cell stays readable (a warning can name hundreds of
    geoms)."""
    return text if len(text) <= limit else text[:limit - 1] + "…"


def mujoco_rollout(m: mujoco.MjModel, qd0: np.ndarray, steps: int, factor: int):
    """qpos after each of ``steps`` model timesteps, MuJoCo at timestep / factor, and whether any contact occurred."""
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = m.qpos0, qd0
    mujoco.mj_forward(m, d)
    qs, contact = [], d.ncon > 0
    for _ in range(steps):
        for _ in range(factor):
            mujoco.mj_step(m, d)
            contact |= d.ncon > 0
        qs.append(d.qpos.copy())
    return np.array(qs), bool(contact)


def torchsim_rollout(sys, m: mujoco.MjModel, qd0: np.ndarray, steps: int, budget: float):
    """torchsim's q after each step (fewer if ``budget`` seconds run out) and whether it diverged."""
    state = torchsim.init(sys, torch.tensor(m.qpos0[None].copy()), torch.tensor(qd0[None]))
    ctrl, qs, t0 = torch.zeros(1, m.nu, dtype=F64), [], time.perf_counter()
    for _ in range(steps):
        state = torchsim.step(sys, state, ctrl)
        qs.append(state.q[0].numpy().copy())
        if time.perf_counter() - t0 > budget:
            break
    return np.array(qs), bool(state.diverged.any()) or not bool(np.isfinite(qs).all())


def q_error(m: mujoco.MjModel, a: np.ndarray, b: np.ndarray) -> float:
    """RMS over time and qpos coordinates of a - b: hinges wrapped to (-pi, pi], quaternions up to sign."""
    diff = a - b
    for j in range(m.njnt):
        i, kind = int(m.jnt_qposadr[j]), m.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_HINGE:
            diff[:, i] = -np.remainder(-diff[:, i] + np.pi, 2 * np.pi) + np.pi
        elif kind in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            s = slice(i + 3, i + 7) if kind == mujoco.mjtJoint.mjJNT_FREE else slice(i, i + 4)
            sign = np.where((a[:, s] * b[:, s]).sum(1, keepdims=True) < 0, -1.0, 1.0)
            diff[:, s] = a[:, s] - sign * b[:, s]
    return float(np.sqrt(np.mean(diff**2)))


def check(source: str, path: Path, budget: float, max_hull_vertices: int | None = None, rollout: bool = True) -> dict:
    """One table row for the model at ``path``; ``max_hull_vertices``: ``torchsim.load_mjcf``'s, and MuJoCo rolls
    out the model torchsim is built from (``torchsim.io_mjcf.mujoco_model``: its colliding hulls capped too);
    ``rollout``: whether a loaded model is rolled out (or only loaded)."""
    t0 = time.perf_counter()
    row = dict(source=source, model=path.stem, status="", nq="-", contact="-", steps="-", ts=np.nan, mj=np.nan,
               verdict="", again={}, detail="")

    def mujoco_model():
        with warnings.catch_warnings():  # the loader's warning names the meshes capped (in the row's detail)
            warnings.simplefilter("ignore")
            return torchsim.io_mjcf.mujoco_model(path, max_hull_vertices)

    try:
        m = mujoco_model()
    except Exception as e:
        return row | dict(status="MJ-ERROR", detail=f"MuJoCo: {e}", time=time.perf_counter() - t0)
    row["nq"] = m.nq
    options = dict(max_hull_vertices=max_hull_vertices)
    row["status"], sys, row["detail"] = load(path, **options)
    if sys is not None and m.nq == 0:
        row["detail"] = "no joints: nothing to roll out"
    elif sys is not None and not rollout:
        row["detail"] = "; ".join(filter(None, ["loaded only, not rolled out", row["detail"]]))
    elif sys is not None:
        steps = int(round(HORIZON / m.opt.timestep))
        qd0 = np.random.default_rng(SEED).normal(0.0, VEL_STD, m.nv)
        ref, contact = mujoco_rollout(m, qd0, steps, 1)
        m4 = mujoco_model()
        m4.opt.timestep /= 4
        fine, contact4 = mujoco_rollout(m4, qd0, steps, 4)
        try:
            ours, diverged = torchsim_rollout(sys, m, qd0, steps, budget)
        except Exception as e:
            row["status"], row["detail"] = "CRASH", f"in step: {type(e).__name__}: {e}"
        else:
            n = len(ours)
            row |= dict(contact="yes" if contact or contact4 else "no",
                        steps=f"{n}" + ("" if n == steps else f"/{steps}"),
                        ts=q_error(m, ours, fine[:n]), mj=q_error(m, ref[:n], fine[:n]))
            tol = max((5.0 if row["contact"] == "yes" else 2.0) * row["mj"], 1e-3)
            row["verdict"] = "MISS" if diverged or not row["ts"] <= tol else "PASS"
            notes = ["torchsim diverged" if diverged else ""]
            for contact_model in AGAIN if row["contact"] == "yes" else ():
                status, again_sys, detail = load(path, contact_model=contact_model, **options)
                if again_sys is not None and again_sys.num_contacts > SOFT_CONTACT_POINTS_WARN:
                    # the budget is checked between steps, and one step of a dense solve this size may take minutes
                    status, detail = "SKIP", (f"{again_sys.num_contacts} contact points, over the "
                                              f"{SOFT_CONTACT_POINTS_WARN} of the loader's dense-solve warning")
                if status != "LOAD":  # refused, crashed or skipped where the impulse contacts loaded
                    row["again"][contact_model] = (np.nan, status)
                    notes.append(f"{contact_model}: {detail}")
                    continue
                again, again_diverged = torchsim_rollout(again_sys, m, qd0, steps, budget)
                error = q_error(m, again, fine[:len(again)])
                row["again"][contact_model] = (error, "MISS" if again_diverged or not error <= tol else "PASS")
            row["detail"] = "; ".join(filter(None, notes + [row["detail"]]))
    if (source, path.stem) in TEMPLATES:
        row["detail"] = "; ".join(filter(None, ["template: the task builds its model from it in code", row["detail"]]))
    return row | dict(time=time.perf_counter() - t0)


def progress_line(r: dict) -> str:
    """A checked model's row as one console line."""
    return (f"{r['source']:18s} {r['model'][:50]:50s} {r['status']:8s} {r['verdict']:4s} ts {fmt(r['ts'])} "
            f"mj {fmt(r['mj'])} " + " ".join(f"{c} {fmt(e)} {v:4s}" for c, (e, v) in r["again"].items())
            + f" {r['time']:6.1f} s  {r['detail'][:90]}")


def provenance(script: str, versions: dict, total: float) -> str:
    """How a table was made: the command as run, the date, the machine and the versions."""
    cmd = " ".join([f"OMP_NUM_THREADS=1 python studies/{script}", *_sys.argv[1:]])
    return (f"`{cmd}` ({datetime.now(timezone.utc):%Y-%m-%d}, 2-core AMD EPYC VM, CPU, float64; "
            f"{', '.join(f'{d} {v}' for d, v in versions.items())}, MuJoCo {mujoco.__version__}, "
            f"torch {torch.__version__}, Python {platform.python_version()}; {total:.0f} s in all).")


def fmt(x: float) -> str:
    return "-" if np.isnan(x) else f"{x:.2e}"


def table(rows: list[dict]) -> str:
    again = "".join(f"| {c}: ratio | {c}: verdict " for c in AGAIN)
    lines = ["| source | model | nq | status | contact | steps | ts vs mj dt/4 | mj dt vs dt/4 | ratio | verdict "
             f"{again}| time [s] | detail |", "|" + "---|" * (12 + 2 * len(AGAIN))]

    def ratio(x, r):
        return "-" if np.isnan(x) or not r["mj"] > 0 else f"{x / r['mj']:.3g}"

    for r in rows:
        detail = r["detail"].replace("|", "/").split("; see torchsim")[0]
        lines.append(f"| {r['source']} | {r['model']} | {r['nq']} | {r['status']} | {r['contact']} | {r['steps']} "
                     f"| {fmt(r['ts'])} | {fmt(r['mj'])} | {ratio(r['ts'], r)} | {r['verdict'] or '-'} "
                     + "".join(f"| {ratio(e, r)} | {v} " for e, v in (r["again"].get(c, (np.nan, "-")) for c in AGAIN))
                     + f"| {r['time']:.1f} | {f'`{detail}`' if detail else ''} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    status = collections.Counter(r["status"] for r in rows)
    verdict = collections.Counter(r["verdict"] for r in rows if r["verdict"])

    names_and_counts = r"'[^']*'|\(\d+ found\)|#\d+|(?<=has )\d+(?= vertices)"  # what differs between models
    causes = collections.Counter(re.sub(names_and_counts, "…", r["detail"]).split("; ")[0]
                                 for r in rows if r["status"] == "REFUSE")
    out = [f"{len(rows)} models: " + ", ".join(f"{k} {v}" for k, v in sorted(status.items())) + "; rolled out: "
           + (", ".join(f"{k} {v}" for k, v in sorted(verdict.items())) or "none")
           + "".join(f"; with contacts, under `contact_model=\"{c}\"`: " + (", ".join(
               f"{k} {v}" for k, v in sorted(collections.Counter(
                   r["again"][c][1] for r in rows if c in r["again"]).items())) or "none") for c in AGAIN) + "."]
    out += ["", "Refusal causes:"] + [f"- {n} x `{c}`" for c, n in causes.most_common()]
    crashes = [f"- {r['source']}/{r['model']}: `{r['detail']}`" for r in rows if r["status"] == "CRASH"]
    return "\n".join(out + (["", "Crashes (engine bugs):"] + crashes if crashes else []))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "torchsim" / "third_party")
    for dist, (version, _) in PACKAGES.items():
        parser.add_argument(f"--{dist.replace('_', '-')}", dest=dist, default=version, help=f"{dist} version")
    parser.add_argument("--models", nargs="+", help="only models with these file stems (e.g. ant cartpole)")
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per torchsim rollout before it is cut")
    parser.add_argument("--write-docs", action="store_true", help=f"write the table into {DOCS.relative_to(ROOT)}")
    args = parser.parse_args()
    torch.set_num_threads(1)

    versions = {dist: getattr(args, dist) for dist in PACKAGES}
    paths = model_paths(args.cache, versions)
    print(f"{len(paths)} models (" + ", ".join(f"{d} {versions[d]}: {sum(s == d for s, _ in paths)}"
                                              for d in PACKAGES) + ")", flush=True)
    paths = [(s, p) for s, p in paths if not args.models or p.stem in args.models]
    rows, t0 = [], time.perf_counter()
    for source, path in paths:
        rows.append(check(source, path, args.budget))
        print(progress_line(rows[-1]), flush=True)
    total = time.perf_counter() - t0
    text = "\n\n".join([
        provenance("check_third_party.py", versions, total) + " Rule, rollout and verdict: the script's docstring. "
        "`ts`: torchsim vs MuJoCo at dt/4; `mj`: MuJoCo dt vs dt/4; RMS of qpos over 0.5 s from qpos0 with "
        "N(0, 0.1) start velocities, zero controls; PASS: ts <= max(2 mj, 1e-3) without contact, max(5 mj, 1e-3) "
        "with contact. `soft`, `articulated`: the same torchsim rollout with `load_mjcf(contact_model=...)` "
        "(MuJoCo's soft contact normal, `torchsim/soft_contacts.py`; velocities, limits and contacts solved "
        "through the articulation, `torchsim/tree_solve.py`), for the models with contact. dm_control's lqr.xml and "
        "swimmer.xml are templates (see the docstring).",
        summary(rows), table(rows)])
    print("\n" + text)
    if args.write_docs:
        replace_section(DOCS, SECTION, text, keep_subsections=True)  # the hand-written reading below survives
        print(f"\nwrote {SECTION!r} in {DOCS}")


if __name__ == "__main__":
    main()
