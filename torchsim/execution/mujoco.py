"""MuJoCo C's physics behind a Stepper's call: ``state = stepper(state, ctrl)`` advances the same MJCF one
``sys.timestep`` in MuJoCo (``mujoco.rollout``) instead of in torchsim: one MuJoCo step, or ``substeps`` steps of
``timestep / substeps`` with the control held (MuJoCo nearer its converged answer: on contact-rich models its own
step is far from it, ``docs/transfer_gap.md``).

An env built with ``stepper=MujocoStepper(...)`` runs its own observation, reward, termination and reset code on
MuJoCo's physics, which is what a policy-transfer measure needs: the same task code on both simulators, the
simulator the only difference (``python -m torchsim.evaluate physics=mujoco``, ``studies/policy_transfer.py``).

Each call copies ``q`` and ``qd`` into MuJoCo's state, steps once with the control held, and rebuilds torchsim's
body poses from MuJoCo's ``qpos``/``qvel`` (``torchsim.init``), so everything an env reads of a State is MuJoCo's.
MuJoCo's solver warm start does not survive the round trip (each step starts its contact solve cold); the actuators'
activations (``na > 0``) travel as ``State.act``. The System's mocap poses (``mocap_pos``/``mocap_quat``, one for all
envs or per env) are MuJoCo's ``mocap_pos``/``mocap_quat`` in every step; ``for_system`` takes a System that differs
in them only.
"""

import copy
import dataclasses

import mujoco
import mujoco.rollout
import numpy as np
import torch

from torchsim import pipeline
from torchsim.state import State
from torchsim.system import System


class MujocoStepper:
    """Steps ``sys``'s model in MuJoCo C on ``threads`` threads (default: one per CPU core torch uses).

    Args:
        sys: the torchsim System of the same MJCF (it builds the returned States; ``stepper.sys``).
        model: MuJoCo's model of that MJCF (an env's ``mj_model``).
        substeps: MuJoCo steps per ``sys.timestep`` (each ``timestep / substeps``, the control held); 1: MuJoCo
            as the model is.
    """

    strategy = "mujoco"

    def __init__(self, sys: System, model: mujoco.MjModel, threads: int | None = None, substeps: int = 1):
        if (model.nq, model.nv, model.nu, model.na) != (sys.nq, sys.nv, sys.nu, sys.na):
            raise ValueError(f"MujocoStepper: the MuJoCo model (nq, nv, nu, na) = "
                             f"{(model.nq, model.nv, model.nu, model.na)} is not the System's "
                             f"{(sys.nq, sys.nv, sys.nu, sys.na)}")
        if not isinstance(substeps, int) or isinstance(substeps, bool) or substeps < 1:
            raise ValueError(f"MujocoStepper: substeps must be a positive integer, got {substeps!r}")
        if substeps > 1:
            model = copy.deepcopy(model)  # the caller's model keeps its timestep
            model.opt.timestep /= substeps
        self.sys = sys
        self.model = model
        self.substeps = substeps
        self._datas = [mujoco.MjData(model) for _ in range(threads or torch.get_num_threads())]
        self._spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self._template = np.empty(mujoco.mj_stateSize(model, self._spec))
        mujoco.mj_getState(model, self._datas[0], self._template, self._spec)
        # FULLPHYSICS starts time, qpos, qvel, act (MuJoCo's mjtState order)
        self._qpos = slice(1, 1 + model.nq)
        self._qvel = slice(1 + model.nq, 1 + model.nq + model.nv)
        self._act = slice(1 + model.nq + model.nv, 1 + model.nq + model.nv + model.na)

    def __call__(self, state: State, ctrl: torch.Tensor) -> State:
        batch = state.q.shape[0]
        start = np.tile(self._template, (batch, 1))
        start[:, 0] = 1.0  # time: MuJoCo resets an env whose accelerations blow up, which sets its time to 0
        start[:, self._qpos] = state.q.detach().cpu().double().numpy()
        start[:, self._qvel] = state.qd.detach().cpu().double().numpy()
        start[:, self._act] = state.act.detach().cpu().double().numpy()
        control, spec = ctrl.detach().cpu().double().numpy(), mujoco.mjtState.mjSTATE_CTRL
        if self.model.nmocap:
            mocap = [x.detach().expand(batch, *x.shape[-2:]).reshape(batch, -1).cpu().double().numpy()
                     for x in (self.sys.mocap_pos, self.sys.mocap_quat)]
            control = np.concatenate((control, *mocap), -1)
            spec = spec | mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT
        out = np.empty((batch, self.substeps, start.shape[1]))
        mujoco.rollout.rollout(self.model, self._datas, start, np.repeat(control[:, None, :], self.substeps, 1),
                               control_spec=int(spec), nstep=self.substeps, state=out)
        out = out[:, -1]
        as_tensor = lambda x: torch.as_tensor(x, dtype=self.sys.dtype, device=self.sys.device)  # noqa: E731
        q, qd, act = (as_tensor(out[:, part]) for part in (self._qpos, self._qvel, self._act))
        stepped = torch.as_tensor(out[:, 0] > 1.0, device=q.device)
        ok = stepped & torch.isfinite(q).all(-1) & torch.isfinite(qd).all(-1) & torch.isfinite(act).all(-1)
        # an env MuJoCo reset (or left non-finite) keeps its last state and is flagged, as torchsim's own step
        # contains a divergence
        q = torch.where(ok[:, None], q, state.q)
        qd = torch.where(ok[:, None], qd, state.qd)
        act = torch.where(ok[:, None], act, state.act)
        return pipeline.init(self.sys, q, qd, act)._replace(diverged=state.diverged | ~ok)

    def for_system(self, sys: System) -> "MujocoStepper":
        """This stepper for ``sys``, which may differ from its System in the mocap poses only (what an env's
        ``set_mocap`` or a task moving its mocap targets makes)."""
        if sys is self.sys:
            return self
        if all(getattr(sys, f.name) is getattr(self.sys, f.name) for f in dataclasses.fields(sys)
               if f.name not in ("mocap_pos", "mocap_quat")):
            other = object.__new__(MujocoStepper)
            other.__dict__.update(self.__dict__, sys=sys)
            return other
        raise NotImplementedError("MujocoStepper: per-env physics parameters (set_physics) are torchsim's; MuJoCo's "
                                  "model has one set")
