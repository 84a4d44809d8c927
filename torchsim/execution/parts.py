"""A batch stepped as parts of a few hundred envs, spread over worker threads: how compiled CPU steps run.

Envs never interact, so a batch can be cut anywhere and each part stepped as an ordinary ``step`` of a smaller
batch; joined, the parts give the whole-batch result exactly. Two things make that faster on CPU
(measured in commit 6bce6de, its ``docs/benchmarks.md``):

- **Part size.** Inductor's substep kernel streams ~120 intermediate buffers (~21 KB per env) through ~140 loop
  nests. Parts of a few hundred ant envs ran 1.1-1.5x faster per env than one part of 4096 on one thread (the
  gain varied between runs), and 1.1-1.25x faster than halves of 2048 on two.
- **Threads.** The kernel gains nothing from OpenMP threads (its loop nests are each too short to share), but
  parts on separate threads scale: the compiled kernels release the GIL. Each thread steps its share of the parts
  one after another.

A ``torchsim.Stepper`` whose strategy compiles the step as loop nests (``loop``, ``calls``) steps CPU batches this
way (its ``part_size`` and ``threads``); eager steps stay whole and on one thread (their Python dispatch would
hold the GIL most of the time, and eager ops gain from large batches), and so do step kernels (one loop over the
whole batch, spread over every intra-op thread).
"""

import itertools
import math
import threading
from concurrent.futures import ThreadPoolExecutor

import torch

from torchsim.state import State
from torchsim.system import System


class Parts:
    """How a stepper cuts CPU batches: parts of at most ``size`` envs (0: whole batches), stepped on ``workers``
    threads (``workers - 1`` in a pool: the calling thread steps its share too). Each compiled stepper owns one."""

    def __init__(self, size: int, workers: int):
        if size < 0 or workers < 1:
            raise ValueError(f"part size must be >= 0 and workers >= 1, got {size} and {workers}")
        self.size, self.workers = size, workers
        self.pool = ThreadPoolExecutor(workers - 1, thread_name_prefix="torchsim-part") if workers > 1 else None
        self.lock = threading.Lock()
        self.warm = set()  # (method, dtype, part sizes) stepped once, i.e. whose compilation is done

    def sizes(self, state: State) -> list[int]:
        """Sizes of the parts ``state``'s batch is stepped in: ``ceil(B / size)`` parts of near-equal size (one
        size when ``B`` is a multiple of the part size, so that one static compilation serves them all); one part
        when parts are off or off the CPU."""
        batch = state.x_pos.shape[0]
        if self.size == 0 or state.x_pos.device.type != "cpu":
            return [batch]
        count = max(1, math.ceil(batch / self.size))
        return [batch // count + (k < batch % count) for k in range(count)]

    def step(self, step, sys: System, state: State, ctrl: torch.Tensor, sizes: list[int]) -> State:
        """``step(sys, state, ctrl)`` on consecutive slices of the batch of ``sizes``, joined into one State; each
        worker thread steps a contiguous share of the parts."""
        batch = state.x_pos.shape[0]
        bounds = [0, *itertools.accumulate(sizes)]
        jobs = [(system_part(sys, batch, a, b), State(*(x[a:b] for x in state)), ctrl[a:b])
                for a, b in zip(bounds[:-1], bounds[1:])]
        key = (sys.method, sys.dtype, tuple(sorted(set(sizes))))
        with self.lock:
            first_run = key not in self.warm
            self.warm.add(key)
        threads = 1 if first_run else min(self.workers, len(jobs))  # first run: compile on this thread alone
        cuts = [len(jobs) * k // threads for k in range(threads + 1)]
        shares = [jobs[a:b] for a, b in zip(cuts[:-1], cuts[1:])]

        grad, inference = torch.is_grad_enabled(), torch.is_inference_mode_enabled()

        def run(share):  # grad and inference mode are per thread: the workers step in the caller's
            with torch.inference_mode(inference), torch.set_grad_enabled(grad):
                return [step(*job) for job in share]

        futures = [self.pool.submit(run, share) for share in shares[1:]]
        results = run(shares[0]) + [r for f in futures for r in f.result()]
        return State(*(torch.cat(fields) for fields in zip(*results)))


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

    wheres, ranks = zip(*sys.batchable())
    return sys.with_parameters(list(wheres), [part(sys.parameter(w), r) for w, r in zip(wheres, ranks)])
