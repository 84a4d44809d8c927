"""Chart training runs side by side: evaluation return against wall clock and against env steps.

    python studies/plot_peer.py --torchsim-log outputs/ppo_ant/<run>/train.log --torchsim-start 11:52:39 \
        --brax docs/logs/brax_ppo_ant.csv --out docs/training_peer_brax_ant.png
    python studies/plot_peer.py --run "torchsim physics=docs/logs/a.log@05:09:35" \
        --run "MuJoCo physics=docs/logs/b.log@04:49:00" --title "Hopper, PPO" --target 2000 --out hopper.png

``--run LABEL=LOG@HH:MM:SS`` adds any ``python -m torchsim.train`` console log (repeatable).

``--torchsim-start`` is the wall-clock time (HH:MM:SS) the ``python -m torchsim.train`` process started (e.g.
``ps -o lstart``), so both curves count from their process's start, compiling included. The Brax CSV comes from
``benchmarks/brax_peer_ppo_ant.py``. Prints each run's first evaluation at or above ``--target``.
"""

import argparse
import csv
import datetime
import re

EVAL_LINE = re.compile(r"^\[(\d\d:\d\d:\d\d)\].* steps\s+([\d,]+) .* eval\s+([-\d.]+)")


def seconds(hms: str) -> int:
    t = datetime.datetime.strptime(hms, "%H:%M:%S")
    return t.hour * 3600 + t.minute * 60 + t.second


def torchsim_evals(log_path, start_hms):
    rows, t0 = [], seconds(start_hms)
    for line in open(log_path):
        m = EVAL_LINE.match(line)
        if m:
            rows.append(((seconds(m[1]) - t0) % 86400, int(m[2].replace(",", "")), float(m[3])))
    if not rows:
        raise SystemExit(f"no evaluation lines in {log_path}")
    return rows


def brax_evals(csv_path):
    with open(csv_path) as f:
        return [(float(r["wall_s"]), int(r["env_steps"]), float(r["eval_return"])) for r in csv.DictReader(f)]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--torchsim-log")
    p.add_argument("--torchsim-start", help="HH:MM:SS the training process started")
    p.add_argument("--brax", help="Brax's evaluations (benchmarks/brax_peer_ppo_ant.py's CSV)")
    p.add_argument("--run", action="append", default=[], metavar="LABEL=LOG@HH:MM:SS",
                   help="another torchsim.train console log, started at HH:MM:SS (repeatable)")
    p.add_argument("--target", type=float, default=4000.0)
    p.add_argument("--title", default="Ant, PPO, 2 CPU cores, same machine and session")
    p.add_argument("--out", default="training_peer_brax_ant.png")
    args = p.parse_args()
    runs = {}
    if args.torchsim_log:
        if not args.torchsim_start:
            raise SystemExit("--torchsim-log needs --torchsim-start (HH:MM:SS the process started)")
        runs["torchsim PPO (python -m torchsim.train)"] = torchsim_evals(args.torchsim_log, args.torchsim_start)
    if args.brax:
        runs["Brax PPO (brax 0.14.2, JAX CPU, spring)"] = brax_evals(args.brax)
    for run in args.run:
        label, sep, rest = run.rpartition("=")
        log_path, at, start = rest.rpartition("@")
        if not (sep and at):
            raise SystemExit(f"--run wants LABEL=LOG@HH:MM:SS, got {run!r}")
        runs[label] = torchsim_evals(log_path, start)
    if not runs:
        raise SystemExit("nothing to chart: give --torchsim-log, --brax or --run")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_time, by_steps) = plt.subplots(1, 2, figsize=(12, 4.2))
    for name, rows in runs.items():
        wall_min = [r[0] / 60 for r in rows]
        by_time.plot(wall_min, [r[2] for r in rows], "o-", ms=3, label=name)
        by_steps.plot([r[1] / 1e6 for r in rows], [r[2] for r in rows], "o-", ms=3, label=name)
        hit = next((r for r in rows if r[2] >= args.target), None)
        print(f"{name}: " + (f"first eval >= {args.target:.0f}: {hit[2]:.0f} at {hit[0] / 60:.1f} min, "
                             f"{hit[1] / 1e6:.2f}M env steps" if hit else f"never >= {args.target:.0f}"))
    for ax, xlabel in ((by_time, "wall clock from process start (min), compiling included"),
                       (by_steps, "env steps (millions)")):
        ax.axhline(args.target, color="grey", lw=0.8, ls="--")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("deterministic eval return")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.suptitle(args.title)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
