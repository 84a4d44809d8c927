"""Training recipes on TorchRL: ``ppo`` and ``sac`` (loops), ``common`` (envs, networks, evaluation, run
bookkeeping), ``configs/`` (Hydra). Entry points: ``python -m torchsim.train`` and ``python -m torchsim.evaluate``."""
