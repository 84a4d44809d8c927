"""Training configs the tests run in about a second (no engine code here)."""

from hydra import compose, initialize_config_dir

from torchsim.algos.train import CONFIG_DIR

#: PPO iterations of 16 env steps on eager physics (``budget.env_steps / 16`` of them; two by default): a real run,
#: with its checkpoint, in about a second
TINY_PPO = ["algo=ppo", "env=inverted_pendulum", "algo.num_envs=8", "algo.unroll=2", "algo.minibatches=2",
            "budget.env_steps=32", "eval.episodes=2", "eval.max_steps=5", "video.enabled=false", "logger=''",
            "compile=false", "threads=1"]


def tiny_ppo(*overrides):
    """The composed config of a :data:`TINY_PPO` run with ``overrides``."""
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=[*TINY_PPO, *overrides])
