"""MuJoCo bodies -> torchsim bodies: each body without joints is fused into its parent (its weld root).

Mocap bodies (MuJoCo ``body_mocapid >= 0``) are kinematic: their pose is the System's ``mocap_pos``/``mocap_quat``,
set per env, which the weld and connect constraints (``torchsim.welds``) and the contacts of their geoms
(``torchsim.collision``) read. They are not moving bodies: their masses and jointless children belong to the static
world, which takes no impulse, and their geoms move with the mocap frame (:meth:`FusedBodies.moving_frame`), at rest
as in MuJoCo. A body attached to a mocap body by joints is refused by name.

Frames here are numpy float64, MuJoCo's ``(pos, quat)`` convention.
"""

from typing import NamedTuple

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.subset import UnsupportedMJCFError, name


class FusedBodies(NamedTuple):
    """How MuJoCo's bodies map onto torchsim's ``N`` fused bodies.

    Attributes:
        roots: MuJoCo id of each fused body's weld root, in torchsim body order.
        index: MuJoCo weld root (or 0, the world, or a mocap body) -> torchsim ext body index (the world is ``N``).
        frame: MuJoCo body -> its ``(pos (3,), quat (4,))`` in its weld root's frame (the world's: identity; a mocap
            body's: the world's at the model pose, where its geoms stay).
        com: ``(N, 3)`` each fused body's centre of mass in its root's frame [m].
        mocap: MuJoCo id of each mocap body, in MuJoCo's ``body_mocapid`` order.
    """

    roots: list
    index: dict
    frame: dict
    com: np.ndarray
    mocap: list

    def body_of(self, m: mujoco.MjModel, mj_body: int) -> int:
        """The torchsim ext body index that MuJoCo body ``mj_body`` is fused into."""
        return self.index[m.body_weldid[mj_body]]

    def moving_frame(self, m: mujoco.MjModel, mj_body: int) -> tuple[int, np.ndarray, np.ndarray]:
        """The frame MuJoCo body ``mj_body`` moves with, as an index into the ext bodies followed by the mocap
        bodies (``N + 1 + k`` for mocap body ``k``, as ``torchsim.welds.frames`` lists them), and the body's
        ``(pos (3,), quat (4,))`` in it: from its fused body's COM, the world's origin, or the mocap body's origin
        in the mocap body's own frame."""
        root = m.body_weldid[mj_body]
        pos, quat = self.frame[mj_body]
        if m.body_mocapid[root] < 0:
            return self.body_of(m, mj_body), pos - self.com_of(m, mj_body), quat
        root_pos, root_quat = self.frame[root]  # the mocap body's model pose in the world
        inverse = np.zeros(4)
        mujoco.mju_negQuat(inverse, root_quat)
        pos, quat = compose(np.zeros(3), inverse, pos - root_pos, quat)
        return len(self.roots) + 1 + int(m.body_mocapid[root]), pos, quat

    def com_of(self, m: mujoco.MjModel, mj_body: int) -> np.ndarray:
        """The COM of the fused body holding ``mj_body`` in its root's frame (the world's origin for the world)."""
        body = self.index[m.body_weldid[mj_body]]
        return self.com[body] if body < len(self.roots) else np.zeros(3)


def compose(pos_a, quat_a, pos_b, quat_b):
    """Frame b given in frame a -> frame b in a's parent."""
    quat = np.zeros(4)
    mujoco.mju_mulQuat(quat, quat_a, quat_b)
    return pos_a + quat_mat(quat_a) @ pos_b, quat


def quat_mat(q) -> np.ndarray:
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, q)
    return rot.reshape(3, 3)


def fuse_bodies(m: mujoco.MjModel) -> tuple[FusedBodies, dict]:
    """Fuse each jointless body into its weld root, combining mass, COM and inertia in the root's frame: the
    mapping, and the System's body fields."""
    identity = (np.zeros(3), np.array([1.0, 0, 0, 0]))
    frame = {0: identity}
    mocap = sorted((b for b in range(1, m.nbody) if m.body_mocapid[b] >= 0), key=lambda b: m.body_mocapid[b])
    for b in range(1, m.nbody):  # a mocap body's parent is the world: its model pose is its body_pos, body_quat
        kept = m.body_weldid[b] == b and m.body_mocapid[b] < 0
        frame[b] = identity if kept else compose(*frame[m.body_parentid[b]], m.body_pos[b], m.body_quat[b])
    roots = [b for b in range(1, m.nbody) if m.body_weldid[b] == b and m.body_mocapid[b] < 0]
    index = {0: len(roots)} | {b: len(roots) for b in mocap} | {b: i for i, b in enumerate(roots)}
    _check_mocap(m, roots)
    mass, com, inertia = np.zeros(len(roots)), np.zeros((len(roots), 3)), np.zeros((len(roots), 3, 3))
    for i, r in enumerate(roots):
        members = [b for b in range(1, m.nbody) if m.body_weldid[b] == r]
        coms, tensors = [], []
        for b in members:
            rot = quat_mat(compose(*frame[b], np.zeros(3), m.body_iquat[b])[1])
            coms.append(frame[b][0] + quat_mat(frame[b][1]) @ m.body_ipos[b])
            tensors.append(rot @ np.diag(m.body_inertia[b]) @ rot.T)
        masses = m.body_mass[members]
        mass[i] = masses.sum()
        if mass[i] <= 0:
            raise UnsupportedMJCFError(f"body {name(m, mujoco.mjtObj.mjOBJ_BODY, r)!r} has no mass")
        com[i] = (masses[:, None] * np.array(coms)).sum(0) / mass[i]
        for mb, c, t in zip(masses, coms, tensors):  # parallel-axis theorem about the fused COM
            d = c - com[i]
            inertia[i] += t + mb * (d @ d * np.eye(3) - np.outer(d, d))
    fused = FusedBodies(roots, index, frame, com, mocap)
    mj_pos = np.array([frame[b][0] - fused.com_of(m, b) for b in range(m.nbody)])
    mocap_quat = m.body_quat[mocap].reshape(-1, 4)
    return fused, dict(
        mocap_pos=torch.as_tensor(m.body_pos[mocap].reshape(-1, 3).copy()),
        mocap_quat=torch.as_tensor(mocap_quat / np.linalg.norm(mocap_quat, axis=-1, keepdims=True)),
        body_mass=torch.as_tensor(mass), body_inertia=torch.as_tensor(inertia), body_ipos=torch.as_tensor(com),
        body_parent=torch.as_tensor([fused.body_of(m, m.body_parentid[r]) for r in roots], dtype=torch.long),
        body_names=tuple(name(m, mujoco.mjtObj.mjOBJ_BODY, r) for r in roots),
        mjbody_body=torch.as_tensor([fused.body_of(m, b) for b in range(m.nbody)], dtype=torch.long),
        mjbody_pos=torch.as_tensor(mj_pos), mjbody_quat=torch.as_tensor(np.array([frame[b][1] for b in range(m.nbody)])),
    )


def _check_mocap(m: mujoco.MjModel, roots: list) -> None:
    """Refuse a body attached to a mocap body by joints (its joint would hold it to the model pose)."""
    for b in roots:
        mocap = m.body_weldid[m.body_parentid[b]]
        if m.body_mocapid[mocap] >= 0:
            raise UnsupportedMJCFError(
                f"body {name(m, mujoco.mjtObj.mjOBJ_BODY, b)!r} is attached to mocap body "
                f"{name(m, mujoco.mjtObj.mjOBJ_BODY, mocap)!r} by joints: torchsim's mocap bodies carry only rigidly "
                "attached bodies (weld the body to the mocap body with an <equality><weld> instead)")
