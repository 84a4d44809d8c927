"""Train PPO or SAC on a torchsim env: ``python -m torchsim.train [algo=ppo|sac] [env=<name>] [key=value ...]``
(``torchsim/train.py`` runs this module).

Configs live in ``torchsim/algos/configs`` (``--cfg job`` prints the composed one, a run writes it resolved to
``config.yaml`` in its run dir); outputs (CSV logs, checkpoints,
``curves.png``, ``policy.gif``, ``summary.json``) go to the Hydra run dir ``outputs/<algo>_<env>/<time>/`` (with
``_1``, ``_2``, ... appended where another run started in the same second).
"""

import itertools
import logging
import os
import pathlib
import sys
import tempfile

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

import torchsim.algos
import torchsim.progress
from torchsim.algos import apg, ppo, sac
from torchsim.algos.common import Run, TrainingDiverged
from torchsim.algos.distributed import Ranks

CONFIG_DIR = str(pathlib.Path(torchsim.algos.__file__).parent / "configs")
RECIPES = {"ppo": ppo.train, "sac": sac.train, "apg": apg.train}


def fresh_run_dir(base: str) -> str:
    """Create and return ``base``, or ``base_1``, ``base_2``, ... where it exists: a run's own directory even when
    another run started in the same second (each name is taken by an exclusive mkdir, so two processes, on one
    machine or on two sharing the disk, never get the same one). The config's ``hydra.run.dir`` is
    ``${fresh_dir:...}``; cached, as Hydra's ``now``, so that every read of the config sees one directory."""
    path = pathlib.Path(base)
    path.parent.mkdir(parents=True, exist_ok=True)
    for n in itertools.count():
        candidate = path.with_name(f"{path.name}_{n}") if n else path
        try:
            candidate.mkdir()
        except FileExistsError:
            continue
        return str(candidate)


OmegaConf.register_new_resolver("fresh_dir", fresh_run_dir, use_cache=True, replace=True)


def run(cfg: DictConfig, out_dir) -> Run:
    """Run the recipe ``cfg.algo.name`` with ``cfg``, writing into ``out_dir``; return the finished run. Under
    ``torchrun`` this process is one rank of a data-parallel run (``torchsim.algos.distributed``)."""
    check_config(cfg)
    ranks = Ranks.from_env(cfg.device)
    try:
        prepare(cfg, ranks)
        return RECIPES[cfg.algo.name](cfg, out_dir, ranks)
    finally:
        ranks.close()


def tuned_settings(cfg: DictConfig) -> str:
    """Which per-pair settings the composed config holds: the tuned file for ``cfg``'s algo and env, or that there
    is none (the config's defaults list takes it where it exists, silently)."""
    name = f"{cfg.algo.name}_{cfg.env.name}"
    tuned = pathlib.Path(CONFIG_DIR, "tuned", f"{name}.yaml")
    if tuned.exists():
        return f"settings: algos/configs/tuned/{name}.yaml over algo/{cfg.algo.name}.yaml and env/{cfg.env.name}.yaml"
    return (f"settings: no tuned file for {cfg.algo.name} on {cfg.env.name} (algos/configs/tuned/{name}.yaml): the "
            f"untuned defaults of algo/{cfg.algo.name}.yaml and env/{cfg.env.name}.yaml")


def write_config(cfg: DictConfig, out_dir) -> pathlib.Path:
    """Write every setting of the run, resolved (tuned file, recipe and overrides applied; no interpolations), to
    ``<out_dir>/config.yaml``, the one file to read for what a run used; return its path. (Hydra's
    ``.hydra/config.yaml`` beside it keeps the interpolations, ``.hydra/overrides.yaml`` the command line.)"""
    path = pathlib.Path(out_dir, "config.yaml")
    path.write_text(OmegaConf.to_yaml(cfg, resolve=True))
    return path


def check_config(cfg: DictConfig) -> None:
    """Refuse settings the run would only trip on later: the iteration counts between progress lines and between
    checkpoints divide the iteration number (0 would stop the first iteration with a ZeroDivisionError)."""
    for key in ("print_every", "checkpoint_every"):
        value = cfg[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{key} must be a positive number of iterations, got {value!r}")


def prepare(cfg: DictConfig, ranks: Ranks = Ranks()) -> None:
    """The process-wide settings a run of ``cfg`` uses: compile announcements, threads (a rank's share of the
    machine's cores where ``cfg.threads`` is null and several ranks share it), seed (``seed + rank``: every rank
    draws its own envs; rank 0's networks are broadcast). The envs' steppers follow ``compile_physics``
    (``torchsim.algos.physics_task.make_base``)."""
    torchsim.progress.announce_torch_compiles()
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its storage-allocation notices are not progress
    threads = cfg.threads if cfg.threads is not None or not ranks.parallel else ranks.threads()
    if threads is not None:
        torch.set_num_threads(threads)
    torch.manual_seed(cfg.seed + ranks.rank)


def stopped_message(out_dir, overrides: list[str]) -> str:
    """What a run stopped with Ctrl-C says: the command that continues it from its last checkpoint (the run's own
    overrides, which a resumed run must repeat, and ``resume=``), or that it wrote none yet."""
    last = pathlib.Path(out_dir) / "checkpoints" / "last.pt"
    if not last.exists():
        return "stopped (Ctrl-C) before the run's first checkpoint"
    kept = [o for o in overrides if not o.startswith(("hydra.", "resume="))]
    return ("stopped (Ctrl-C); continue from the last checkpoint with:\n  python -m torchsim.train "
            + " ".join([*kept, f"resume={last}"]))


def stopped_by_ctrl_c(err: BaseException) -> bool:
    """Whether ``err`` is Ctrl-C's ``KeyboardInterrupt`` or was raised while one unwound: a library's clean-up that
    fails on the way out (a tensordict context manager's ``__exit__``) must not turn a stop into a crash."""
    while err is not None:
        if isinstance(err, KeyboardInterrupt):
            return True
        err = err.__context__
    return False


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> None:
    out_dir = HydraConfig.get().runtime.output_dir
    log = logging.getLogger("torchsim.train")
    log.info(tuned_settings(cfg))
    if int(os.environ.get("RANK", "0")) == 0:
        log.info(f"config: {write_config(cfg, out_dir)} (every setting of this run, resolved)")
    try:
        run(cfg, out_dir)
    except TrainingDiverged as err:
        print(f"training diverged: {err}", file=sys.stderr)
        sys.exit(1)
    except BaseException as err:
        if not stopped_by_ctrl_c(err):
            raise
        print(stopped_message(out_dir, list(HydraConfig.get().overrides.task)), file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    if int(os.environ.get("RANK", "0")) > 0:  # under torchrun only rank 0 writes a run directory and a log
        sys.argv += ["hydra.output_subdir=null", "hydra/job_logging=disabled", f"hydra.run.dir={tempfile.gettempdir()}"]
    main()
