"""torchsim: batched maximal-coordinate rigid-body physics in PyTorch.

    sys = torchsim.load_mjcf("ant.xml", method="xpbd")   # static model as tensors
    state = torchsim.init(sys, q, qd)                    # q: (B, nq), qd: (B, nv), MuJoCo layout
    state = torchsim.step(sys, state, ctrl)              # ctrl: (B, nu); advances sys.timestep (the reference)
    stepper = torchsim.Stepper(sys)                      # the same step, compiled by the fastest strategy
    state = stepper(state, ctrl)
"""

import os

# Idle OpenMP threads (torch's pool, which the CPU step kernel shares) spin ~300k times before they sleep, libgomp's
# default: on a machine where another process is busy the spinning threads take the cores the working one needs,
# and the main job fell to 0.06-0.30 of its idle rate; after 1000 spins it keeps 0.4-0.5, idle rate unchanged
# (benchmarks/bench_contention.py, docs/reliability.md). libgomp reads this once, when torch loads it: it applies where
# torchsim is imported before torch (python -m torchsim.train), and an explicit setting wins.
os.environ.setdefault("GOMP_SPINCOUNT", "1000")

from torchsim import kinematics  # noqa: E402
from torchsim.contact_forces import ContactForces, contact_forces  # noqa: E402
from torchsim.io_mjcf import UnsupportedMJCFError, load_mjcf  # noqa: E402
from torchsim.io_urdf import UnsupportedURDFError, load_urdf  # noqa: E402
from torchsim.kinematics import mj_body_poses  # noqa: E402
from torchsim.pipeline import init, step  # noqa: E402
from torchsim.sensors import sensor, sensordata, sensors_by_name  # noqa: E402
from torchsim.state import State  # noqa: E402
from torchsim.execution import Stepper  # noqa: E402
from torchsim.system import System  # noqa: E402

__all__ = ["load_mjcf", "load_urdf", "UnsupportedURDFError", "init", "step", "Stepper", "State", "System",
           "UnsupportedMJCFError", "mj_body_poses", "kinematics", "sensor", "sensordata", "sensors_by_name",
           "contact_forces", "ContactForces"]
