"""Throughput timing shared by the benchmarks (and the studies that time or start MuJoCo: speed_accuracy.py,
scene_cost.py, transfer_step_error.py): the median rate of a repeated call, MuJoCo C's batched ``mujoco.rollout``
as the baseline, and the tables they print."""

import statistics
import time
from collections.abc import Callable

import mujoco
import mujoco.rollout
import numpy as np


def allow_recompiles(limit: int = 64) -> None:
    """Let dynamo compile a function up to ``limit`` times (a benchmark's batch sizes, substep counts and models):
    torch 2.13 checks ``recompile_limit``, older releases ``cache_size_limit``."""
    import torch

    for name in ("cache_size_limit", "recompile_limit"):
        if hasattr(torch._dynamo.config, name):
            setattr(torch._dynamo.config, name, max(getattr(torch._dynamo.config, name), limit))


def emit_table(table: str, out: str | None, log: Callable[[str], None] = print) -> None:
    """Show a markdown ``table`` and, given a path ``out``, write it there too."""
    log(table)
    if out:
        with open(out, "w") as f:
            f.write(table + "\n")


def median_rate(run: Callable[[], None], units: float, repeats: int, min_seconds: float = 0.5) -> float:
    """Median over ``repeats`` of ``units`` x calls / seconds, each repeat calling ``run`` until ``min_seconds`` have
    passed (enough calls that the timer's and the call's fixed overheads do not dominate)."""
    rates = []
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while calls == 0 or time.perf_counter() - start < min_seconds:
            run()
            calls += 1
        rates.append(units * calls / (time.perf_counter() - start))
    return statistics.median(rates)


def alternating_rates(runs: dict[str, Callable[[], None]], units: float, repeats: int, min_seconds: float = 0.5
                      ) -> dict[str, list[float]]:
    """Each run's rate (as ``median_rate``: ``units`` x calls / seconds over at least ``min_seconds``) in each of
    ``repeats`` repeats, the runs taking turns within a repeat: a drift of the machine's speed then reaches them all
    alike, so ratios between runs are best taken repeat by repeat."""
    rates = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            rates[name].append(median_rate(run, units, 1, min_seconds))
    return rates


def mujoco_start_states(m: mujoco.MjModel, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """(batch, nstate) full-physics states of ``m`` at generalized positions ``q`` and velocities ``qd`` (batch, .)."""
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    d = mujoco.MjData(m)
    states = np.empty((len(q), mujoco.mj_stateSize(m, spec)))
    for b in range(len(q)):
        d.qpos[:], d.qvel[:] = q[b], qd[b]
        mujoco.mj_getState(m, d, states[b], spec)
    return states


def mujoco_rollout_rate(m: mujoco.MjModel, start: np.ndarray, ctrl: np.ndarray, repeats: int,
                        threads: int = 1) -> float:
    """MuJoCo steps/s (batch x nstep / s) of ``mujoco.rollout`` on ``threads`` threads from ``start`` (batch,
    nstate) under ``ctrl`` (batch, nstep, nu), after one untimed warm-up rollout."""
    datas = [mujoco.MjData(m) for _ in range(threads)]
    batch, nstep = ctrl.shape[:2]
    out = np.empty((batch, nstep, start.shape[1]))

    def run():
        mujoco.rollout.rollout(m, datas, start, ctrl, nstep=nstep, state=out)

    run()
    return median_rate(run, batch * nstep, repeats)
