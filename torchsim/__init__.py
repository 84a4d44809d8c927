"""torchsim: batched maximal-coordinate rigid-body physics in PyTorch.

    sys = torchsim.load_mjcf("ant.xml", method="xpbd")   # static model as tensors
    state = torchsim.init(sys, q, qd)                    # q: (B, nq), qd: (B, nv), MuJoCo layout
    state = torchsim.step(sys, state, ctrl)              # ctrl: (B, nu); advances sys.timestep (the reference)
    stepper = torchsim.Stepper(sys)                      # the same step, compiled by the fastest strategy
    state = stepper(state, ctrl)
"""

from torchsim import kinematics
from torchsim.io_mjcf import UnsupportedMJCFError, load_mjcf
from torchsim.io_urdf import UnsupportedURDFError, load_urdf
from torchsim.kinematics import mj_body_poses
from torchsim.pipeline import init, step
from torchsim.state import State
from torchsim.execution import Stepper
from torchsim.system import System

__all__ = ["load_mjcf", "load_urdf", "UnsupportedURDFError", "init", "step", "Stepper", "State", "System",
           "UnsupportedMJCFError", "mj_body_poses", "kinematics"]
