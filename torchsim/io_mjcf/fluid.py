"""MuJoCo's ``<option density viscosity wind>`` -> torchsim fluid elements (``torchsim.fluid``).

MuJoCo's inertia-box model acts on every MuJoCo body on its own (its box from that body's own principal inertia and
mass, at its own COM and inertial frame), even where torchsim fuses jointless bodies into one: so the elements are
MuJoCo's bodies, each carried by the fused body it belongs to. ``geom fluidshape="ellipsoid"`` (the newer
ellipsoid model) is refused naming the geom.
"""

import mujoco
import numpy as np
import torch

from torchsim.io_mjcf.bodies import FusedBodies, compose, quat_mat
from torchsim.io_mjcf.subset import UnsupportedMJCFError, name


def fluid_fields(m: mujoco.MjModel, fused: FusedBodies) -> dict:
    """The System's ``fluid*`` fields (``System`` documents them); no elements where the fluid is off."""
    for g in range(m.ngeom):
        if m.geom_fluid[g, 0] > 0:
            raise UnsupportedMJCFError(
                f"geom {name(m, mujoco.mjtObj.mjOBJ_GEOM, g)!r}: fluidshape=\"ellipsoid\" (MuJoCo's ellipsoid fluid "
                "model) is not supported; torchsim has the inertia-box model (no fluidshape)")
    flags = m.opt.disableflags
    passive_off = flags & int(mujoco.mjtDisableBit.mjDSBL_SPRING) and flags & int(mujoco.mjtDisableBit.mjDSBL_DAMPER)
    on = (m.opt.viscosity > 0 or m.opt.density > 0) and not passive_off  # MuJoCo's own conditions (mj_passive)
    # MuJoCo skips massless bodies; bodies welded to the world never move, whatever the fluid pushes
    elements = [b for b in range(1, m.nbody) if on and m.body_mass[b] >= mujoco.mjMINVAL and m.body_weldid[b]]
    body, pos, rot, damping, drag = [], [], [], [], []
    for b in elements:
        frame_pos, frame_quat = compose(*fused.frame[b], m.body_ipos[b], m.body_iquat[b])
        body.append(fused.body_of(m, b))
        pos.append(frame_pos - fused.com_of(m, b))
        rot.append(quat_mat(frame_quat))
        i0, i1, i2 = m.body_inertia[b]
        # the box with the body's mass and principal inertia: I_x = M (b_y^2 + b_z^2) / 12, ...
        box = np.sqrt(np.maximum(mujoco.mjMINVAL, np.array([i1 + i2 - i0, i0 + i2 - i1, i0 + i1 - i2]))
                      / m.body_mass[b] * 6.0)
        diam = box.mean()  # the diameter of the sphere standing in for the box in Stokes' law
        mu, rho = m.opt.viscosity, m.opt.density
        damping.append([np.pi * diam ** 3 * mu] * 3 + [3.0 * np.pi * diam * mu] * 3)
        b4 = box ** 4
        drag.append(list(rho * box * (b4.sum() - b4) / 64.0)  # MuJoCo's drag of the box spinning about each axis
                    + list(0.5 * rho * np.prod(box) / box))  # the face area normal to each axis
    return dict(
        fluid=bool(elements),
        fluid_body=torch.as_tensor(body, dtype=torch.long),
        fluid_pos=torch.as_tensor(np.array(pos, dtype=float).reshape(-1, 3)),
        fluid_rot=torch.as_tensor(np.array(rot, dtype=float).reshape(-1, 3, 3)),
        fluid_damping=torch.as_tensor(np.array(damping, dtype=float).reshape(-1, 6)),
        fluid_drag=torch.as_tensor(np.array(drag, dtype=float).reshape(-1, 6)),
        fluid_wind=torch.as_tensor(m.opt.wind.copy()),
    )
