"""What a training run writes survives concurrency and faults: run directories are unique even for runs started in
the same second, checkpoints are fsynced before an atomic rename (a failed write leaves the last one intact, and
no temp file), the last two are kept, and ranks above 0 write files of their own names."""

import os
import pathlib
import threading

import hydra.core.utils
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from tensordict import TensorDict

from torchsim.algos.checkpoints import load_checkpoint
from torchsim.algos.common import Run, TrainingDiverged
from torchsim.algos.distributed import Ranks
from torchsim.algos.env_factory import compiles
from torchsim.algos.train import CONFIG_DIR, fresh_run_dir, run, write_config
from tiny_runs import TINY_PPO, tiny_ppo


# ------------------------------------------------------------------------------------------------- run directories
def test_the_run_dir_holds_every_setting_resolved(tmp_path):
    """``config.yaml`` in the run dir: the composed config with the tuned file and overrides applied and every
    interpolation resolved (``eval.max_steps`` is ``${env.episode_length}`` in config.yaml)."""
    cfg = tiny_ppo("eval.max_steps=${env.episode_length}", "substeps=3")
    written = OmegaConf.load(write_config(cfg, tmp_path))
    assert written == OmegaConf.to_container(cfg, resolve=True)
    assert written.eval.max_steps == cfg.env.episode_length and written.substeps == 3
    assert "${" not in (tmp_path / "config.yaml").read_text()


@pytest.mark.parametrize("overrides, physics, loss", [
    ([], True, True), (["compile=false"], False, False), (["compile=false", "compile_loss=true"], False, True),
    (["compile_physics=false"], False, True)])
def test_compile_splits_into_physics_and_loss(overrides, physics, loss):
    """``compile`` is the shorthand for ``compile_physics`` and ``compile_loss`` where they are null; a checkpoint's
    config from before the split (``compile`` only) reads as the shorthand."""
    cfg = tiny_ppo("compile=true", *overrides)
    assert (compiles(cfg, "physics"), compiles(cfg, "loss")) == (physics, loss)
    old = OmegaConf.create({"compile": False})
    assert not compiles(old, "physics") and not compiles(old, "loss")


def test_runs_started_in_the_same_second_get_their_own_directories(tmp_path, monkeypatch):
    """Two runs whose clocks read the same second: Hydra's ``now`` is frozen, as it reads for two runs started
    together; each run's ``hydra.run.dir`` is a directory of its own, created as the config is read."""
    monkeypatch.chdir(tmp_path)
    dirs = []
    for _ in range(2):
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            OmegaConf.register_new_resolver("now", lambda pattern: "2025-01-01_12-00-00", use_cache=True,
                                            replace=True)
            try:
                cfg = compose(config_name="config", overrides=TINY_PPO, return_hydra_config=True)
                dirs.append(cfg.hydra.run.dir)
                assert cfg.hydra.run.dir == dirs[-1]  # read again: the same directory, not a third one
            finally:
                hydra.core.utils.setup_globals()  # Hydra's own now
    assert dirs == ["outputs/ppo_inverted_pendulum/2025-01-01_12-00-00",
                    "outputs/ppo_inverted_pendulum/2025-01-01_12-00-00_1"]
    assert all((tmp_path / d).is_dir() for d in dirs)
    assert len(list((tmp_path / "outputs" / "ppo_inverted_pendulum").iterdir())) == 2


def test_run_directories_are_taken_exclusively(tmp_path):
    """Eight threads ask for the same directory at once: each gets a different one."""
    base, got = str(tmp_path / "runs" / "same_second"), []
    barrier = threading.Barrier(8)

    def take():
        barrier.wait()
        got.append(fresh_run_dir(base))

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(set(got)) == 8 and all(pathlib.Path(d).is_dir() for d in got)
    assert sorted(got) == sorted([base] + [f"{base}_{n}" for n in range(1, 8)])


# ---------------------------------------------------------------------------------------------------- checkpoints
def bare_run(out_dir, ranks: Ranks = Ranks()) -> Run:
    """A Run with one small network as its whole state, and no envs: its checkpoints and files, nothing else."""
    net = torch.nn.Linear(3, 2)
    return Run(tiny_ppo(), out_dir, {"net": net}, net, None, None, ranks)


def test_checkpoints_keep_the_last_two(tmp_path):
    """Three iterations, a checkpoint after each: last.pt holds the third, previous.pt the second, and the final
    save does not push the second out by writing the third again."""
    run(tiny_ppo("checkpoint_every=1", "budget.env_steps=48"), tmp_path)
    folder = tmp_path / "checkpoints"
    assert sorted(p.name for p in folder.iterdir()) == ["last.pt", "previous.pt"]
    assert load_checkpoint(folder / "last.pt")["counters"]["iteration"] == 3
    assert load_checkpoint(folder / "previous.pt")["counters"]["iteration"] == 2


def test_checkpoint_is_fsynced_before_it_replaces_the_last(tmp_path, monkeypatch):
    """The new checkpoint's data reach the disk before any rename (else a crash after the rename can leave last.pt
    empty), and the directory is synced after the renames."""
    saver = bare_run(tmp_path)
    saver.save()
    events = []
    fsync, replace = os.fsync, os.replace

    def spy_fsync(fd):
        events.append(("fsync", pathlib.Path(os.readlink(f"/proc/self/fd/{fd}")).name))
        fsync(fd)

    def spy_replace(src, dst):
        events.append(("replace", pathlib.Path(src).name, pathlib.Path(dst).name))
        replace(src, dst)

    monkeypatch.setattr(os, "fsync", spy_fsync)
    monkeypatch.setattr(os, "replace", spy_replace)
    saver.iteration = 1
    saver.save()
    temp = events[0][1]
    assert temp.startswith(".last.pt.") and temp.endswith(".tmp")  # a name of its own beside last.pt
    assert events == [("fsync", temp), ("replace", "last.pt", "previous.pt"), ("replace", temp, "last.pt"),
                      ("fsync", "checkpoints")]


def test_failed_checkpoint_write_keeps_the_last_good_one(tmp_path, monkeypatch):
    """A write that dies half way (a full disk) leaves last.pt as it was and no partial temp file."""
    saver = bare_run(tmp_path)
    saver.save()
    save = torch.save

    def disk_full(obj, f, *args, **kwargs):  # writes part of the checkpoint to the path or file it is given
        if isinstance(f, (str, os.PathLike)):
            pathlib.Path(f).write_bytes(b"half a checkpoint")
        else:
            f.write(b"half a checkpoint")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    saver.iteration = 1
    with pytest.raises(OSError, match="No space left"):
        saver.save()
    monkeypatch.setattr(torch, "save", save)
    folder = tmp_path / "checkpoints"
    assert [p.name for p in folder.iterdir()] == ["last.pt"]
    assert load_checkpoint(folder / "last.pt")["counters"]["iteration"] == 0


def test_ranks_write_diverged_minibatches_to_their_own_files(tmp_path):
    """Every rank stops on the same non-finite step and saves its minibatch; ranks above 0 share the temp dir (as
    every run's ranks above 0 do), so their files must not overwrite each other or rank 0's."""
    saved = []
    for rank in (0, 1, 2):
        with pytest.raises(TrainingDiverged) as err:
            bare_run(tmp_path, Ranks(rank, 3)).check_update(
                {"loss_objective": torch.tensor(float("nan"))}, torch.tensor(1.0),
                TensorDict(rank=torch.full((2,), rank)))
        path = pathlib.Path(str(err.value).split("minibatch saved to ")[1].split(";")[0])
        assert path.parent == tmp_path
        saved.append(path.name)
    assert saved[0] == "diverged_minibatch.pt"
    assert "rank1" in saved[1] and "rank2" in saved[2] and len(set(saved)) == 3
    assert sorted(p.name for p in tmp_path.glob("diverged_minibatch*")) == sorted(saved)  # none overwritten
