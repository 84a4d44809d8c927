"""Policy transfer as a fidelity measure: a policy trained on one simulator's physics, run on the
other's, with the same task code.

For each checkpoint (a training run's ``checkpoints/last.pt``) the deterministic policy runs ``--episodes`` episodes
on the physics it trained on and on the other one (torchsim or MuJoCo C, through ``torchsim.execution.mujoco``), from
the same start states (``seed``), with the same observation, reward, termination and observation normaliser. The
ratio of the mean returns (other / trained-on) says how much of the policy's skill survives the change of simulator:
1.0 where the two simulators agree on everything the policy exploits.

    python studies/policy_transfer.py outputs/ppo_ant/<run>/checkpoints/last.pt ...       # table on stdout
    python studies/policy_transfer.py <checkpoint> --seed 7 --mujoco-substeps 2 4 20      # and MuJoCo at dt/2, dt/4,
                                                                                          # dt/20 (mujoco_substeps)
    python studies/policy_transfer.py --write-docs <checkpoints>                          # and into docs/physics.md
    python -m torchsim.train env=hopper physics=mujoco        # a policy trained in MuJoCo, for the reverse direction
"""

import argparse
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from _docs import replace_section
from torchsim.algos.evaluate import main as evaluate

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs" / "physics.md"
SECTION = "## Policy transfer between torchsim and MuJoCo"
OTHER = {"torchsim": "mujoco", "mujoco": "torchsim"}


def transfer(checkpoint: Path, episodes: int, seed: int, splits: list[int]) -> dict:
    """Mean returns of ``checkpoint``'s policy on the physics it trained on and on the other one; on MuJoCo also
    with its model timestep split into each of ``splits`` (``row["split"][n]``)."""
    def run(label: str, *physics: str) -> dict:
        start = time.perf_counter()
        result = evaluate([f"checkpoint={checkpoint}", f"episodes={episodes}", f"seed={seed}", *physics])
        print(f"  {result['env']} on {result['physics']}{label}: return {result['return_mean']:.0f} +- "
              f"{result['return_std']:.0f}, length {result['episode_length_mean']:.0f} "
              f"({time.perf_counter() - start:.0f} s)", flush=True)
        return result

    trained = run("")
    other = OTHER[trained["trained_on"]]
    row = {"env": trained["env"], "algo": trained["algo"], "env_steps": trained["env_steps_trained"],
           "trained_on": trained["trained_on"], "trained": trained, "other": run("", f"physics={other}"),
           "split": {n: run(f" at dt/{n}", "physics=mujoco", f"mujoco_substeps={n}") for n in splits}
           if other == "mujoco" else {}}
    row["ratio"] = row["other"]["return_mean"] / trained["return_mean"]
    return row


def table(rows: list[dict], episodes: int, splits: list[int]) -> str:
    """The transfer table; a column per MuJoCo timestep split (its return there, length, and ratio to the
    trained-on return)."""
    lines = ["| env (algo, env steps trained) | trained on | return there (length) | run on | return there (length) "
             "| ratio |" + "".join(f" MuJoCo at dt/{n} (ratio) |" for n in splits),
             "|---|---|---:|---|---:|---:|" + "---:|" * len(splits)]
    for r in rows:
        t, o = r["trained"], r["other"]
        split = "".join(f" {r['split'][n]['return_mean']:.0f} ({r['split'][n]['episode_length_mean']:.0f}, "
                        f"{r['split'][n]['return_mean'] / t['return_mean']:.2f}) |" if n in r["split"] else " - |"
                        for n in splits)
        lines.append(f"| {r['env']} ({r['algo']}, {r['env_steps'] / 1e6:.1f}M) | {t['physics']} | "
                     f"{t['return_mean']:.0f} +- {t['return_std']:.0f} ({t['episode_length_mean']:.0f}) | "
                     f"{o['physics']} | {o['return_mean']:.0f} +- {o['return_std']:.0f} "
                     f"({o['episode_length_mean']:.0f}) | {r['ratio']:.2f} |{split}")
    return "\n".join(lines) + f"\n\nMean +- std over {episodes} episodes from the same start states on both."


def write_docs(text: str, command: str) -> None:
    """Replace the section's table, keeping the hand-written ``###`` notes below it."""
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d")
    replace_section(DOCS, SECTION, f"Measured {stamp}: `{command}`\n\n{text}", keep_subsections=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mujoco-substeps", type=int, nargs="*", default=[],
                        help="also run torchsim-trained policies on MuJoCo with its timestep split into each N")
    parser.add_argument("--write-docs", action="store_true", help=f"write the table into {DOCS.relative_to(ROOT)}")
    args = parser.parse_args()
    torch.set_num_threads(min(2, torch.get_num_threads()))
    rows = []
    for checkpoint in args.checkpoints:
        print(f"{checkpoint}:", flush=True)
        rows.append(transfer(checkpoint, args.episodes, args.seed, args.mujoco_substeps))
    text = table(rows, args.episodes, args.mujoco_substeps)
    print(text)
    if args.write_docs:
        command = "python studies/policy_transfer.py " + " ".join(sys.argv[1:]).replace("--write-docs ", "")
        write_docs(text, command)


if __name__ == "__main__":
    main()
