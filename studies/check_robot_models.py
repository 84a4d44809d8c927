"""Robot model check: every MJCF file in dm_control's, gymnasium-robotics' and robosuite's published
wheels that MuJoCo compiles on its own, loaded by torchsim, and each loaded movable one rolled out passively
against MuJoCo as ``studies/check_third_party.py`` does (same rollout, errors and verdict; its docstring).

Model set: every ``*.xml`` anywhere in the three packages; a file MuJoCo cannot compile by itself (an include
fragment, a robot or gripper part that robosuite assembles in code, a file whose assets are missing) is not a
standalone model and is only counted. "Movable": ``nv > 0``; "with meshes": a mesh geom, colliding or not.

Each model is checked as it is, and again with ``load_mjcf(max_hull_vertices=64)`` where that caps a colliding
mesh's hull (``torchsim.io_mjcf.hull_caps``), MuJoCo rolling out the capped model too; the other models are the same
with the option, and their rows are counted again as they are. Counts, verdicts and refusal causes are given both
ways. ``--capped-load-only``: the capped models are loaded, not rolled out (an eager step of a robot of many
64-vertex mesh pairs takes seconds to minutes: Fetch's rows took 8 minutes each). ``--load-only``: no model is
rolled out, for the counts and refusal causes alone (~2 minutes; a full run's soft-contact rollout of dm_control's
dog_v2 spends over 10 minutes in its first step, which the rollout budget cannot cut).

    OMP_NUM_THREADS=1 python studies/check_robot_models.py                  # all, summary and table on stdout
    OMP_NUM_THREADS=1 python studies/check_robot_models.py --write-docs     # and into docs/models.md
    python studies/check_robot_models.py --packages robosuite --match panda --budget 5

The wheels are downloaded (``pip download --no-deps``) into ``--cache`` and unzipped there on first use.
"""

import argparse
import collections
import time
from pathlib import Path

import mujoco
import torch

from _docs import replace_section
from check_third_party import DOCS, ROOT, check, fetch, progress_line, provenance, summary, table
from torchsim.io_mjcf.hull_caps import colliding_meshes, hull_vertex_count
from torchsim.io_mjcf.meshes import MAX_HULL_VERTICES

SECTION = "## Robot models of dm_control, gymnasium-robotics and robosuite"
# distribution -> (default version, folder searched inside the wheel)
PACKAGES = {
    "dm_control": ("1.0.50", "dm_control"),
    "gymnasium_robotics": ("1.4.2", "gymnasium_robotics"),
    "robosuite": ("1.5.2", "robosuite"),
}


def standalone_models(cache: Path, versions: dict, packages: list[str], match: str | None):
    """(source, path, model) of every file MuJoCo compiles by itself, and how many ``*.xml`` files each package has."""
    found, files = [], collections.Counter()
    for dist in packages:
        folder = fetch(cache, dist, versions[dist]) / PACKAGES[dist][1]
        for path in sorted(folder.rglob("*.xml")):
            if match and match not in str(path.relative_to(folder)):
                continue
            files[dist] += 1
            try:
                found.append((dist, path, mujoco.MjModel.from_xml_path(str(path))))
            except Exception:  # noqa: BLE001 - not a standalone model (the module docstring)
                pass
    return found, files


def counts(rows: list[dict], models: dict, files: collections.Counter, packages: list[str]) -> str:
    """Per package: files, standalone models, and how many of those (movable, movable with meshes) load."""
    lines = ["| package | xml files | standalone | load | movable | movable, load | movable with meshes | "
             "movable with meshes, load |", "|" + "---|" * 8]
    total = collections.Counter()
    for dist in [*packages, "all"]:
        mine = [r for r in rows if dist in (r["source"], "all")]
        movable = [r for r in mine if models[r["key"]].nv > 0]
        meshed = [r for r in movable if (models[r["key"]].geom_type == mujoco.mjtGeom.mjGEOM_MESH).any()]
        c = dict(files=files[dist] if dist != "all" else sum(files.values()), standalone=len(mine),
                 load=sum(r["status"] == "LOAD" for r in mine), movable=len(movable),
                 movable_load=sum(r["status"] == "LOAD" for r in movable), meshed=len(meshed),
                 meshed_load=sum(r["status"] == "LOAD" for r in meshed))
        total.update(c)
        pct = lambda a, b: f"{c[a]} ({100 * c[a] / c[b]:.0f} %)" if c[b] else "0"  # noqa: E731
        lines.append(f"| {dist} | {c['files']} | {c['standalone']} | {pct('load', 'standalone')} | {c['movable']} "
                     f"| {pct('movable_load', 'movable')} | {c['meshed']} | {pct('meshed_load', 'meshed')} |")
    return "\n".join(lines)


def capped(m: mujoco.MjModel) -> bool:
    """Whether ``load_mjcf(max_hull_vertices=MAX_HULL_VERTICES)`` caps a colliding mesh's hull of ``m``."""
    return any(hull_vertex_count(m, mesh) > MAX_HULL_VERTICES for mesh in colliding_meshes(m))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, default=Path.home() / ".cache" / "torchsim" / "third_party")
    for dist, (version, _) in PACKAGES.items():
        parser.add_argument(f"--{dist.replace('_', '-')}", dest=dist, default=version, help=f"{dist} version")
    parser.add_argument("--packages", nargs="+", default=list(PACKAGES), choices=list(PACKAGES))
    parser.add_argument("--match", help="only files whose path inside the package contains this")
    parser.add_argument("--budget", type=float, default=10.0, help="seconds per torchsim rollout before it is cut")
    parser.add_argument("--capped-load-only", action="store_true", help="load the capped models, no rollouts")
    parser.add_argument("--load-only", action="store_true", help="load every model, no rollouts")
    parser.add_argument("--write-docs", action="store_true", help=f"write the tables into {DOCS.relative_to(ROOT)}")
    args = parser.parse_args()
    torch.set_num_threads(1)
    versions = {dist: getattr(args, dist) for dist in PACKAGES}
    found, files = standalone_models(args.cache, versions, args.packages, args.match)
    print(f"{len(found)} standalone models of {sum(files.values())} xml files", flush=True)
    rows, capped_rows, models, t0 = [], [], {}, time.perf_counter()
    for dist, path, model in found:
        folder = fetch(args.cache, dist, versions[dist]) / PACKAGES[dist][1]
        name = str(path.relative_to(folder).with_suffix(""))
        row = check(dist, path, args.budget, rollout=not args.load_only) | dict(model=name, key=(dist, name))
        models[row["key"]] = model
        rows.append(row)
        print(progress_line(row), flush=True)
    print(f"again with max_hull_vertices={MAX_HULL_VERTICES}, where it caps a hull", flush=True)
    caps = [capped(model) for _, _, model in found]
    capped_rollout = not (args.capped_load_only or args.load_only)
    for (dist, path, _), row, cap in zip(found, rows, caps):
        if cap:
            row = check(dist, path, args.budget, max_hull_vertices=MAX_HULL_VERTICES,
                        rollout=capped_rollout) | dict(model=row["model"], key=row["key"])
            print(progress_line(row), flush=True)
        capped_rows.append(row)
    total = time.perf_counter() - t0
    changed = [row for row, cap in zip(capped_rows, caps) if cap]
    text = "\n\n".join([
        provenance("check_robot_models.py", {d: versions[d] for d in args.packages}, total) + " Model set, counts "
        "and the second count: the script's docstring; rollout and verdict: `studies/check_third_party.py`'s (each "
        f"torchsim rollout cut after {args.budget:g} s, the steps column says where).",
        "As the models are:", counts(rows, models, files, args.packages), summary(rows),
        f"With `load_mjcf(max_hull_vertices={MAX_HULL_VERTICES})` (MuJoCo's `maxhullvert` on the colliding meshes "
        f"whose hulls have more vertices; {len(changed)} models have such meshes):",
        counts(capped_rows, models, files, args.packages), summary(capped_rows),
        "As the models are:", table(rows),
        f"The {len(changed)} models with `max_hull_vertices={MAX_HULL_VERTICES}`:", table(changed)])
    print("\n" + text)
    if args.write_docs:
        replace_section(DOCS, SECTION, text)
        print(f"\nwrote {SECTION!r} in {DOCS}")


if __name__ == "__main__":
    main()
