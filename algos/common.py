"""A training run (:class:`Run`: progress, logging, checkpoints, budget, plots and the policy video) and the pieces
the recipes share, each in a module of its own: envs (``env_factory``), what differs per task (``tasks``:
``physics_task``, ``nav_task``), evaluation (``evaluation``), checkpoints (``checkpoints``), curves and videos
(``outputs``). The networks are in ``torchsim.algos.networks``."""

import collections
import json
import logging
import os
import pathlib
import time
import warnings

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.record.loggers import get_logger

from torchsim.algos.checkpoints import check_resumable, load_checkpoint, restore_rng, save_checkpoint
from torchsim.algos.distributed import Ranks
from torchsim.algos.env_factory import compiles, obs_norm
from torchsim.algos.evaluation import evaluate
from torchsim.algos.outputs import plot_curves, video

# tensordict reads a deprecated dynamo flag while torch.compile traces the loss (tensordict 0.14, torch 2.13)
warnings.filterwarnings("ignore", message=r"torch._dynamo.config.inline_inbuilt_nn_modules is deprecated")
log = logging.getLogger("torchsim.train")


class TrainingDiverged(RuntimeError):
    """A loss became non-finite; the message names the env step and the last good checkpoint."""


# ------------------------------------------------------------------------------------------------------- a training run
#: ``Run.state`` entries of what a rank's random streams have drawn ahead: the training envs' running episodes
#: (``RunningEpisodes``, APG's ``Rollout``) and PPO's next minibatch order (its sampler draws it as the last runs
#: out). Each rank has its own: only rank 0's are saved, and on resume the other ranks, on streams of their own,
#: start new ones, as rank 0 does from a checkpoint written before these were saved or on another kind of device
#: (whose generators' states do not fit this one's).
EPISODES, MINIBATCH_ORDER = "episodes", "minibatch_order"


class RunningEpisodes:
    """The running episodes of a collector's ``env`` as a ``state_dict``: the collector's carried step (the policy's
    next input, with the episodes' returns and step counts and a recurrent policy's states, which TorchRL 0.14 keeps
    in ``Collector._carrier``) and the env's own state (``episode_state``). A resumed run restores them to continue
    those episodes as the uninterrupted run would: starting new ones draws other random numbers, and the runs
    part."""

    def __init__(self, collector, env: TransformedEnv):
        self.collector, self.env = collector, env

    def state_dict(self) -> dict:
        return {"carrier": self.collector._carrier.to_dict(), "env": self.env.base_env.episode_state()}

    def load_state_dict(self, state: dict) -> None:
        carrier = self.collector._carrier
        self.collector._carrier = TensorDict(state["carrier"], batch_size=carrier.batch_size, device=carrier.device)
        self.env.base_env.load_episode_state(state["env"])


class Run:
    """Bookkeeping of one training run in ``out_dir``: env-step budget and wall clock, progress lines, TorchRL logger,
    periodic deterministic evaluation, checkpoints (``checkpoints/last.pt``, written only after a finite update, so
    it is always the last good state, and ``checkpoints/previous.pt``, the one before), resume, and the final plot
    and video.

    ``state`` maps names to everything with a ``state_dict`` that a resumed run needs (networks, loss module with
    its target networks and temperature, optimisers, learning-rate schedule, observation normaliser, and what the
    random stream has drawn ahead: ``EPISODES``, ``MINIBATCH_ORDER``), loaded in its order. With several ``ranks``
    only rank 0 logs, evaluates (the others pass no ``eval_env``), checkpoints and plots; env steps count every
    rank's.

    A resumed run (``cfg.resume``, ``load``) continues the checkpointed one as if it had not stopped: same state,
    episodes, random streams (rank 0's) and counters, so with the same budget it trains as the uninterrupted run
    would. Its history and wall clock (logs, plots) continue the checkpoint's; ``budget.minutes``, though, counts
    this session's time only, from its start: a resumed run gets the minutes it is given, whatever the run before
    it took. A budget the checkpoint has already reached is refused, as is a config that changes what is learned
    (``RESUMABLE_KEYS``).
    """

    def __init__(self, cfg: DictConfig, out_dir, state: dict, actor, eval_env: TransformedEnv | None, train_env,
                 ranks: Ranks = Ranks()):
        self.cfg, self.out_dir, self.state, self.actor = cfg, pathlib.Path(out_dir), state, actor
        self.eval_env, self.train_env, self.ranks = eval_env, train_env, ranks
        self.device = ranks.device(cfg.device)
        self.logger = get_logger(cfg.logger, logger_name=str(self.out_dir), experiment_name="logs") \
            if ranks.is_main else None
        self.env_steps, self.iteration, self.elapsed = 0, 0, 0.0
        # rows (env_steps, wall_s, value); step_reward: the mean reward per env step of each iteration's batch
        self.history = {"train": [], "eval": [], "eval_success": [], "step_reward": []}
        self.recent = collections.deque(maxlen=cfg.recent_episodes)
        self.recent_success = collections.deque(maxlen=cfg.recent_episodes)  # navigation: STOPs within reach
        self.next_eval = 0 if cfg.eval.at_start else cfg.eval.interval_steps
        self.saved_iteration = None  # the iteration last.pt holds, once this run wrote it
        self.iteration_s = self.eval_s = 0.0  # the last iteration's and evaluation's wall-clock seconds
        self.session_t0 = time.perf_counter()  # budget.minutes counts from here
        if cfg.resume:
            self.load(cfg.resume)
        self.t0 = self.session_t0 - self.elapsed  # the wall clock counts the sessions before this one too
        self.t_last, self.steps_last = time.perf_counter(), self.env_steps
        self.unprinted_s, self.unprinted_steps = 0.0, 0  # training time and env steps since the last progress line
        self.t_collected, self.unprinted_collect_s = self.t_last, 0.0  # when the batch arrived; collecting time

    # -- budget
    @property
    def wall(self) -> float:
        return time.perf_counter() - self.t0

    def finished(self) -> bool:
        return self.spent_budget() is not None

    def spent_budget(self) -> str | None:
        """The budget that is spent, with what was reached, or None: env steps, an eval return reached, or this
        session's wall-clock minutes, where the run also stops early enough that its final evaluation (timed as the
        last one) ends within the budget."""
        b = self.cfg.budget
        session_s = time.perf_counter() - self.session_t0
        if b.env_steps is not None and self.env_steps >= b.env_steps:
            return f"budget.env_steps={b.env_steps} (env step {self.env_steps})"
        if b.minutes is not None and session_s + self.iteration_s + self.eval_s >= 60 * b.minutes:
            return f"budget.minutes={b.minutes}"
        if b.eval_return is not None and self.history["eval"] and self.history["eval"][-1][2] >= b.eval_return:
            return f"budget.eval_return={b.eval_return} (eval return {self.history['eval'][-1][2]:.2f})"
        return None

    # -- per iteration
    def record_batch(self, data) -> None:
        """Count the batch's env steps and collect the returns (and, for navigation, the successes) of the
        episodes that ended in it."""
        self.t_collected = time.perf_counter()  # the iteration's collecting ends here, its learning begins
        self.env_steps += data.numel() * self.ranks.world_size
        done = data["next", "done"].squeeze(-1)
        returns = data["next", "episode_reward"].squeeze(-1)[done]
        self.recent.extend(returns.tolist())
        if "success" in data["next"].keys():
            self.recent_success.extend(data["next", "success"].squeeze(-1)[done].tolist())
        self.step_reward = data["next", "reward"].mean().item()

    def check_update(self, losses, grad_norm: torch.Tensor, minibatch) -> None:
        """Before each optimiser step: stop if a loss term or the gradient norm is non-finite.

        Checking every minibatch (not just the iteration's last) stops before a bad step reaches the weights, so
        the networks and the last checkpoint stay good; the offending minibatch is saved for diagnosis."""
        values = {**{k: v.detach() for k, v in losses.items() if v.numel() == 1}, "grad_norm": grad_norm}
        finite = torch.isfinite(torch.stack([v.reshape(()).float() for v in values.values()]))
        if bool(finite.all()):
            return
        bad = [k for k, ok in zip(values, finite.tolist()) if not ok]
        saved = self.out_dir / self.diverged_file_name()
        saved.parent.mkdir(parents=True, exist_ok=True)
        torch.save(minibatch.detach().cpu(), saved)
        ckpt = self.out_dir / "checkpoints" / "last.pt"
        raise TrainingDiverged(f"non-finite {', '.join(bad)} at env step {self.env_steps} (iteration "
                               f"{self.iteration + 1}); minibatch saved to {saved}; last good checkpoint: "
                               f"{ckpt if ckpt.exists() else 'none'}")

    def diverged_file_name(self) -> str:
        """Where a diverged minibatch goes in ``out_dir``: every rank stops on the same non-finite step, and ranks
        above 0 share the system's temp dir as their ``out_dir`` (``torchsim.algos.train``), with other runs too,
        so their files carry the rank and the process id."""
        if self.ranks.is_main:
            return "diverged_minibatch.pt"
        return f"diverged_minibatch_rank{self.ranks.rank}_pid{os.getpid()}.pt"

    def end_iteration(self, losses: dict) -> None:
        """After an update: log; print a progress line every ``cfg.print_every`` iterations (with the env-steps/s
        of the iterations since the last one) and with every evaluation; evaluate and checkpoint when due."""
        self.iteration += 1
        if not self.ranks.is_main:
            return
        self.iteration_s = time.perf_counter() - self.t_last
        steps = self.env_steps - self.steps_last
        self.unprinted_s, self.unprinted_steps = self.unprinted_s + self.iteration_s, self.unprinted_steps + steps
        self.unprinted_collect_s += self.t_collected - self.t_last
        self.steps_last = self.env_steps
        recent = float(np.mean(self.recent)) if self.recent else float("nan")
        metrics = {**{f"train/{k}": float(v) for k, v in losses.items()}, "train/step_reward": self.step_reward,
                   "time/env_steps_per_s": steps / max(self.iteration_s, 1e-9), "time/wall_s": self.wall}
        if self.recent:
            metrics["train/return"] = recent
            self.history["train"].append((self.env_steps, self.wall, recent))
        success = ""
        if self.recent_success:
            metrics["train/success_rate"] = rate = float(np.mean(self.recent_success))
            success = f"  success {rate:4.0%}"
        self.history["step_reward"].append((self.env_steps, self.wall, self.step_reward))
        self.log(metrics)
        line = (f"[{self.cfg.algo.name} {self.cfg.env.name}] it {self.iteration:4d}  steps {self.env_steps:>11,d}  "
                f"{self.unprinted_steps / max(self.unprinted_s, 1e-9):7.0f} steps/s "
                f"(collect {self.unprinted_collect_s / max(self.unprinted_s, 1e-9):3.0%})  return {recent:8.2f}  "
                f"reward/step {self.step_reward:7.3f}{success}  {self.wall / 60:5.1f} min")
        eval_due = self.env_steps >= self.next_eval or self.finished()
        if eval_due:
            line += self.evaluate() + f" ({self.eval_s:.0f} s)"
            self.next_eval = self.env_steps + self.cfg.eval.interval_steps
        if eval_due or self.iteration % self.cfg.print_every == 0:
            log.info(line)
            self.unprinted_s = self.unprinted_steps = self.unprinted_collect_s = 0
        if self.iteration % self.cfg.checkpoint_every == 0 or self.finished():
            self.save()
        self.t_last = time.perf_counter()  # the next iteration's time and rate leave evaluation and saving out

    def log(self, metrics: dict) -> None:
        if self.logger is not None:
            for k, v in metrics.items():
                self.logger.log_scalar(k, v, step=self.env_steps)

    def evaluate(self) -> str:
        """Evaluate, record and log; return the progress-line text (return, and success for goal tasks)."""
        self.sync_eval_norm()
        start = time.perf_counter()
        result = evaluate(self.eval_env, self.actor, self.cfg.eval.max_steps, seed=self.eval_seed())
        self.eval_s = time.perf_counter() - start
        mean = result.ret.mean().item()
        self.history["eval"].append((self.env_steps, self.wall, mean))
        metrics = {"eval/return": mean, "eval/episode_length": result.length.float().mean().item()}
        text = f"  eval {mean:8.2f}"
        if result.final_distance is not None:
            success = result.success_rate(self.eval_env.base_env.success_distance)
            self.history["eval_success"].append((self.env_steps, self.wall, success))
            metrics.update({"eval/success_rate": success,
                            "eval/final_distance": result.final_distance.mean().item()})
            text += f" (success {success:.0%}, final distance {result.final_distance.median().item():.3f} m)"
        if result.spl is not None:
            success, spl = result.success.float().mean().item(), result.spl.mean().item()
            self.history["eval_success"].append((self.env_steps, self.wall, success))
            self.history.setdefault("eval_spl", []).append((self.env_steps, self.wall, spl))
            metrics.update({"eval/success_rate": success, "eval/spl": spl})
            text += f" (success {success:.0%}, SPL {spl:.3f}, length {result.length.float().mean().item():.0f})"
        self.log(metrics)
        return text

    def eval_seed(self) -> int:
        """``eval.seed``, or where it is null one of each evaluation's own, from the run's seed and env step: fresh
        start states at every evaluation, drawn from a stream of their own, not the training's, so that an
        evaluation (as the one a run makes where its budget ends) leaves the training as it would have been without
        it."""
        if self.cfg.eval.seed is not None:
            return self.cfg.eval.seed
        return int(np.random.SeedSequence([self.cfg.seed, self.env_steps]).generate_state(1)[0])

    def sync_eval_norm(self) -> None:
        """Evaluate with the training normaliser's current statistics, frozen."""
        norm = obs_norm(self.eval_env)
        norm.load_state_dict(obs_norm(self.train_env).state_dict())
        norm.freeze()

    # -- checkpoints
    def save(self) -> pathlib.Path:
        """Write ``checkpoints/last.pt`` (rank 0), the one before it kept as ``checkpoints/previous.pt``: tensors and
        plain containers only, so that it loads with ``weights_only`` (``load_checkpoint``)."""
        path = self.out_dir / "checkpoints" / "last.pt"
        if not self.ranks.is_main:
            return path
        path.parent.mkdir(parents=True, exist_ok=True)
        ckpt = {"cfg": OmegaConf.to_container(self.cfg, resolve=True), "world_size": self.ranks.world_size,
                "state": {k: v.state_dict() for k, v in self.state.items()},
                "actor": self.actor.state_dict(),
                "counters": {"env_steps": self.env_steps, "iteration": self.iteration, "elapsed": self.wall,
                             "next_eval": self.next_eval},
                "recent": {"returns": list(self.recent), "successes": list(self.recent_success)},
                "history": self.history, "rng": torch.get_rng_state()}
        if self.device.type == "cuda":  # the envs' and the policy's draws on the GPU
            ckpt["cuda_rng"] = torch.cuda.get_rng_state(self.device)
        save_checkpoint(ckpt, path, path.with_name("previous.pt"))
        self.saved_iteration = self.iteration
        return path

    def load(self, path) -> None:
        """Continue the run checkpointed at ``path`` (see the class): its tensors load onto this rank's device; rank 0
        continues the checkpoint's random streams and what they drew ahead (``EPISODES``), the other ranks, whose
        streams the checkpoint does not hold, start streams of their own. Refused (ValueError) where the config
        changes what is learned (``check_resumable``) or a budget is already spent."""
        ckpt = load_checkpoint(path, self.device)
        check_resumable(ckpt, self.cfg, self.ranks.world_size, path)
        same_streams = self.ranks.is_main and torch.device(ckpt["cfg"]["device"]).type == self.device.type
        for name, part in self.state.items():
            if name in (EPISODES, MINIBATCH_ORDER) and not (same_streams and name in ckpt["state"]):
                continue  # not this rank's streams, or not saved: drawn anew (EPISODES)
            part.load_state_dict(ckpt["state"][name])
        c = ckpt["counters"]
        self.env_steps, self.iteration, self.elapsed, self.next_eval = (c["env_steps"], c["iteration"], c["elapsed"],
                                                                      c["next_eval"])
        self.history.update(ckpt["history"])
        recent = ckpt.get("recent", {"returns": [], "successes": []})  # absent from checkpoints before it was saved
        self.recent.extend(recent["returns"])
        self.recent_success.extend(recent["successes"])
        if self.ranks.is_main:
            restore_rng(ckpt, self.device)
        else:  # rank 0's stream would make this rank's envs repeat rank 0's
            torch.manual_seed(self.cfg.seed + self.ranks.rank + self.ranks.world_size * self.iteration)
        spent = self.spent_budget()
        if spent is not None:
            raise ValueError(f"cannot resume {path}: its run has already reached {spent}; raise that budget, or set "
                             f"it to null, to train on")
        log.info(f"resumed from {path} at env step {self.env_steps}")

    # -- end of run
    def finish(self) -> None:
        """Save the final checkpoint, plot the curves, render the policy and write ``summary.json`` (rank 0)."""
        if not self.ranks.is_main:
            return
        if self.saved_iteration != self.iteration:  # else last.pt has this state and previous.pt the one before
            self.save()
        plot_curves(self.history, self.out_dir / "curves.png", f"{self.cfg.algo.name} {self.cfg.env.name}")
        if self.cfg.video.enabled:
            self.sync_eval_norm()
            trajectory = evaluate(self.eval_env, self.actor, self.cfg.video.steps, record=True).trajectory
            video(self.eval_env, self.cfg.env.name, trajectory, self.out_dir / "policy.gif")
        self.summary = summary = {"env_steps": self.env_steps, "wall_s": round(self.wall, 1),
                   "env_steps_per_s": round(self.env_steps / max(self.wall, 1e-9), 1),
                   "final_eval_return": self.history["eval"][-1][2] if self.history["eval"] else None}
        if self.history["eval_success"]:
            summary["final_eval_success_rate"] = self.history["eval_success"][-1][2]
        (self.out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        log.info(f"done: {summary}; outputs in {self.out_dir}")


def maybe_compile(loss_module, cfg: DictConfig):
    """``torch.compile`` the loss when ``compiles(cfg, "loss")``. Graph breaks (TorchRL's losses have some) run as Python
    between compiled pieces; a compiler error is raised, never hidden behind a silently slow eager loss."""
    return torch.compile(loss_module) if compiles(cfg, "loss") else loss_module
