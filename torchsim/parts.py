"""A batch stepped as parts on worker threads, so that compiled substeps use every CPU core.

Inductor's CPU kernel for a substep gains nothing from OpenMP threads (its ~140 loop nests are each too short to
share), but envs never interact, so cutting the batch into one part per core and stepping the parts on separate
threads does scale: the compiled kernels release the GIL (``docs/benchmarks.md``, speed pass 5). Each part is an
ordinary ``step`` of a smaller batch, so its results are those of stepping the part alone.

``torchsim.compile_substeps(workers=...)`` switches this on; eager steps stay on one thread (their Python dispatch
would hold the GIL most of the time).
"""

import dataclasses
import threading
from concurrent.futures import ThreadPoolExecutor

import torch

from torchsim.state import State
from torchsim.system import BATCHABLE_RANK, System

#: Smallest part worth a thread: below this, per-call overheads (guards, the GIL-held glue) outweigh the kernel.
MIN_PART = 256


class _Workers:
    """The process-wide worker threads (``count - 1`` of them: the calling thread steps the first part)."""

    def __init__(self):
        self.count = 1
        self.pool = None
        self.lock = threading.Lock()
        self.warm = set()  # (method, dtype, part sizes) stepped once, i.e. whose compilation is done

    def set(self, count: int) -> None:
        if count < 1:
            raise ValueError(f"workers must be >= 1, got {count}")
        if self.pool is not None and count != self.count:
            self.pool.shutdown()
            self.pool = None
        self.count = count
        self.warm.clear()
        if count > 1 and self.pool is None:
            self.pool = ThreadPoolExecutor(count - 1, thread_name_prefix="torchsim-part")


WORKERS = _Workers()


def num_parts(state: State) -> int:
    """How many parts ``state``'s batch is stepped in: one per worker, each at least ``MIN_PART`` envs, CPU only,
    never while dynamo traces (a compiled ``step`` is one graph of the whole batch)."""
    if WORKERS.count == 1 or state.x_pos.device.type != "cpu" or torch.compiler.is_compiling():
        return 1
    return max(1, min(WORKERS.count, state.x_pos.shape[0] // MIN_PART))


def system_part(sys: System, batch: int, start: int, stop: int) -> System:
    """``sys`` for envs ``start:stop`` of a batch of ``batch``: its per-env (batched) parameters sliced, the rest
    shared."""

    def part(x: torch.Tensor, rank: int) -> torch.Tensor:
        if x.ndim == rank:
            return x
        if x.ndim != rank + 1 or x.shape[0] != batch:
            raise ValueError(f"a batched System field must have a leading batch dimension of {batch}, "
                             f"got shape {tuple(x.shape)}")
        return x[start:stop]

    changes = {name: part(getattr(sys, name), rank) for name, rank in BATCHABLE_RANK.items()}
    groups = tuple(g._replace(friction=part(g.friction, 1), margin=part(g.margin, 1))
                   for g in sys.contact_groups)
    return dataclasses.replace(sys, contact_groups=groups, **changes)


def step_in_parts(step, sys: System, state: State, ctrl: torch.Tensor, parts: int) -> State:
    """``step(sys, state, ctrl)`` on ``parts`` slices of the batch at once, one per thread, joined into one State."""
    batch = state.x_pos.shape[0]
    bounds = torch.linspace(0, batch, parts + 1).round().long().tolist()
    jobs = [(system_part(sys, batch, a, b), State(*(x[a:b] for x in state)), ctrl[a:b])
            for a, b in zip(bounds[:-1], bounds[1:])]
    key = (sys.method, sys.dtype, tuple(b - a for a, b in zip(bounds[:-1], bounds[1:])))
    with WORKERS.lock:
        first_run = key not in WORKERS.warm
        WORKERS.warm.add(key)
    if first_run:  # compile in this thread, before the parts run concurrently
        results = [step(*job) for job in jobs]
    else:
        futures = [WORKERS.pool.submit(step, *job) for job in jobs[1:]]
        results = [step(*jobs[0])] + [f.result() for f in futures]
    return State(*(torch.cat(fields) for fields in zip(*results)))
