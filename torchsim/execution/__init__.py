"""How a step runs: everything that executes the reference step (``torchsim.pipeline``) faster, and nothing it
depends on (the physics modules import nothing from here).

- ``stepper``: ``Stepper``, the one table of strategies per (method, device) and the one dispatch.
- ``kernel``: the step as one generated kernel: ``rows`` (row graphs), ``program`` (the row-op contract and the
  step's statements), ``emit_cpp`` (CPU), ``emit_cuda`` (GPU), ``cache`` (on disk), ``step`` (the wiring).
- ``compiled``: the ``torch.compile`` strategies; ``parts``: CPU batches cut into parts on threads.
- ``mujoco``: MuJoCo C behind the same interface, for the same task code on MuJoCo's physics.
"""

from torchsim.execution.stepper import STRATEGIES, Stepper, strategies

__all__ = ["STRATEGIES", "Stepper", "strategies"]
