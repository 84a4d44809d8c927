"""Data-parallel training across processes with ``torch.distributed``, launched by ``torchrun``:

    torchrun --nproc_per_node=2 -m torchsim.train threads=1            # 2 ranks on one machine (gloo on CPU)
    torchrun --nnodes=2 --nproc_per_node=8 --rdzv-backend=c10d --rdzv-endpoint=HOST:29400 \\
        -m torchsim.train device=cuda                                   # 16 GPUs on two machines (NCCL)

``algo.num_envs`` stays the run's whole batch: each of the ``world_size`` ranks simulates ``num_envs / world_size``
envs of its own (seeded ``seed + rank``) on its own device, and learns on them; one all-reduce per optimiser step
averages the gradients, so every rank takes the same step from the same weights (broadcast from rank 0 at the
start). What would otherwise differ between ranks is reduced too: advantages are standardised with the statistics
of every rank's minibatch (as one process standardises its whole minibatch), the epoch's mean KL that may stop an
update early, the observation normaliser's running moments (averaged once per iteration), and whether the run has
finished (rank 0 decides). Rank 0 alone logs, evaluates, checkpoints and plots. A plain ``python -m
torchsim.train`` has one rank, and every reduction here is then a no-op.
"""

import datetime
import os

import torch
import torch.distributed as dist

#: How long a collective waits for a missing rank before it fails (torchrun's agent normally stops the other
#: ranks first, within seconds of one dying).
TIMEOUT = datetime.timedelta(minutes=5)
#: How long the other ranks wait while rank 0 works alone (evaluates, checkpoints, logs) at the end of an iteration:
#: an evaluation of a slow env may take longer than :data:`TIMEOUT`, and a rank that died meanwhile is still
#: caught by torchrun's agent, so this only guards against a rank 0 that hangs.
SOLO_WORK_TIMEOUT = datetime.timedelta(hours=24)


class Ranks:
    """This process's place in a data-parallel run: ``rank`` of ``world_size`` (``local_rank`` on its machine),
    with the reductions a PPO update needs. ``Ranks()`` is a plain single process."""

    def __init__(self, rank: int = 0, world_size: int = 1, local_rank: int = 0, local_world_size: int = 1,
                 comm_device: str = "cpu", solo_work_group=None):
        self.rank, self.world_size = rank, world_size
        self.local_rank, self.local_world_size = local_rank, local_world_size
        self.comm_device = torch.device(comm_device)  # where NCCL's collectives want small tensors (gloo: the CPU)
        self.solo_work_group = solo_work_group  # gloo, SOLO_WORK_TIMEOUT: what `agree` waits on

    @classmethod
    def from_env(cls, device: str, timeout: datetime.timedelta = TIMEOUT,
                 solo_work_timeout: datetime.timedelta = SOLO_WORK_TIMEOUT) -> "Ranks":
        """The ranks ``torchrun`` describes in the environment (``WORLD_SIZE``, ``RANK``, ...), joining its process
        group (NCCL for ``device=cuda``, gloo on CPU; collectives wait ``timeout`` for a missing rank) and a gloo
        group for :meth:`agree` (``solo_work_timeout``); a single process where ``WORLD_SIZE`` is unset or 1."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world == 1:
            return cls()
        cuda = torch.device(device).type == "cuda"
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        if not dist.is_initialized():
            dist.init_process_group("nccl" if cuda else "gloo", timeout=timeout)
        solo_work_group = dist.new_group(backend="gloo", timeout=solo_work_timeout)
        return cls(dist.get_rank(), world, local_rank, int(os.environ.get("LOCAL_WORLD_SIZE", str(world))),
                   f"cuda:{local_rank}" if cuda else "cpu", solo_work_group)

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def parallel(self) -> bool:
        return self.world_size > 1

    def device(self, device: str) -> torch.device:
        """This rank's device: ``cuda`` means the GPU of this rank's local index."""
        device = torch.device(device)
        if device.type == "cuda" and device.index is None and self.parallel:
            return torch.device("cuda", self.local_rank)
        return device

    def threads(self) -> int:
        """CPU threads per rank when the config leaves them to torch: this machine's cores shared by its ranks."""
        return max(1, (os.cpu_count() or 1) // self.local_world_size)

    def shard(self, num_envs: int) -> int:
        """This rank's share of the run's ``num_envs`` envs."""
        if num_envs % self.world_size:
            raise ValueError(f"algo.num_envs ({num_envs}) must divide evenly between the {self.world_size} ranks")
        return num_envs // self.world_size

    def broadcast_(self, tensors) -> None:
        """Overwrite ``tensors`` on every rank with rank 0's values."""
        if self.parallel:
            for t in tensors:
                dist.broadcast(t.data, src=0)

    def average_grads_(self, params) -> None:
        """Replace each parameter's gradient by its mean over the ranks (one all-reduce of all of them)."""
        if not self.parallel:
            return
        grads = [p.grad for p in params if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        flat /= self.world_size
        for g, part in zip(grads, flat.split([g.numel() for g in grads])):
            g.copy_(part.view_as(g))

    def mean(self, value: torch.Tensor) -> torch.Tensor:
        """The mean of ``value`` over the ranks."""
        if not self.parallel:
            return value
        value = value.detach().clone()
        dist.all_reduce(value)
        return value / self.world_size

    def standardize(self, x: torch.Tensor) -> torch.Tensor:
        """``(x - mean) / std`` with the mean and (unbiased) standard deviation of ``x`` on every rank together, the
        standard deviation clamped at 1e-6 (as TorchRL's ``ClipPPOLoss(normalize_advantage=True)`` does for one
        process's minibatch)."""
        moments = torch.stack([x.sum(), (x * x).sum(), torch.tensor(float(x.numel()), device=x.device)]).double()
        if self.parallel:
            dist.all_reduce(moments)
        total, squares, count = moments.unbind()
        mean = total / count
        std = ((squares - count * mean * mean).clamp_min(0.0) / (count - 1)).sqrt()
        return (x - mean.to(x.dtype)) / std.to(x.dtype).clamp_min(1e-6)

    def average_moments_(self, norm) -> None:
        """Average an observation normaliser's running moments (``RunningNorm.moments``: E[x] and E[x^2], equal
        counts on every rank) over the ranks, so that every rank normalises with the statistics of all their
        samples."""
        if not self.parallel:
            return
        for moment in norm.moments():
            moment.copy_(self.mean(moment))

    def agree(self, flag: bool) -> bool:
        """Rank 0's ``flag`` on every rank (e.g. whether the run has finished, which its wall clock decides). The
        call that follows rank 0's work alone (evaluation, checkpoint): the other ranks wait for it up to
        :data:`SOLO_WORK_TIMEOUT`, not the collectives' :data:`TIMEOUT`."""
        if not self.parallel:
            return flag
        value = torch.tensor([float(flag)])
        dist.broadcast(value, src=0, group=self.solo_work_group)
        return bool(value.item())

    def close(self) -> None:
        if self.parallel and dist.is_initialized():
            dist.destroy_process_group()
