"""Gradients of short rollouts against finite differences (float64, CPU, eager; docs/gradients.md).

What is differentiated: a rollout of ``H`` steps from ``init(sys, q0, qd0)`` under controls ``ctrl (H, B, nu)``, and
two scalars of it: a random projection of the final ``(q, qd)`` and a reward summed over the steps
(``sum_t w . qd_t - 0.01 |ctrl_t|^2``). Their gradients with respect to the initial state, the controls and the
System's physical parameters (``System.replace`` with a tensor that requires grad: masses, inertias, actuator gains
and gears, damping, armature, joint stiffness, contact friction, and along one direction the geom sizes) are
compared with fourth-order central differences, every element of every input. The perturbed copies run as one
batch: the state and controls are per env, and so are the batchable parameters (``System.BATCHABLE_RANK``).

Error measure: per input and objective, ``max |autograd - fd| / max |fd|``. Step ``e`` (times the input's scale)
and bound per scene are in each test's docstring, chosen from sweeps of ``e`` (``TORCHSIM_FD_EPS=<e>`` overrides
every test's step; ``-s`` prints each test's largest error): the stencil's truncation is ``O(e^4)``, its rounding
``~ u k |J| / e`` with ``k`` the rounding amplification of the stiff joint springs and projections, and with
contacts the difference is only meaningful while no contact switches (a corner touching or leaving, a point
starting or stopping to slip, a soft impulse reaching its clamp) within ``+-2e``; where one does, the differences
move away from autograd's value as ``e`` grows and converge on it as ``e`` shrinks (measured for every scene here).
"""

import os

import pytest
import torch

import torchsim

F64 = torch.float64
SWEEP_EPS = os.environ.get("TORCHSIM_FD_EPS")  # overrides every test's step: the sweeps in docs/gradients.md

# A 3-link chain without contacts: two hinges about y and one about z (3-D motion), motors, damping, armature and
# joint springs; 5 ms steps of 10 substeps.
CHAIN = """
<mujoco><option timestep="0.005"/>
  <default><joint damping="0.05" armature="0.01" stiffness="0.3"/><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body pos="0 0 1"><joint name="j1" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.04" mass="1.0"/>
      <body pos="0.3 0 0"><joint name="j2" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.03" mass="0.6"/>
        <body pos="0.25 0 0"><joint name="j3" type="hinge" axis="0 0 1"/>
          <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.03" mass="0.4"/>
        </body></body></body></worldbody>
  <actuator><motor joint="j1" gear="1"/><motor joint="j2" gear="2"/><motor joint="j3" gear="1"/></actuator>
</mujoco>"""

# A free box on a plane (friction 0.6), 10 ms steps of 10 substeps.
BOX = """
<mujoco><option timestep="0.01"/><worldbody>
  <geom name="floor" type="plane" size="5 5 0.1" friction="0.6"/>
  <body pos="0 0 0.05"><freejoint/><geom type="box" size="0.1 0.07 0.05" mass="1.0" friction="0.6"/></body>
</worldbody></mujoco>"""

# The same box on slides along x and z and a hinge about y (a planar root, as the hopper's), pushed by a motor
# along x and twisted by one about y: the control gradients through contacts.
PUSHED_BOX = """
<mujoco><option timestep="0.01"/><worldbody>
  <geom name="floor" type="plane" size="5 5 0.1" friction="0.6"/>
  <body pos="0 0 0.05">
    <joint name="x" type="slide" axis="1 0 0"/><joint name="z" type="slide" axis="0 0 1"/>
    <joint name="ry" type="hinge" axis="0 1 0" damping="0.01" armature="0.001"/>
    <geom type="box" size="0.1 0.07 0.05" mass="1.0" friction="0.6"/></body>
</worldbody>
<actuator><motor joint="x" gear="1"/><motor joint="ry" gear="1"/></actuator></mujoco>"""


def rollout(sys, q0, qd0, ctrl, weights):
    """The two objectives ``(B,)`` of a rollout: the projection of its final ``(q, qd)`` on ``weights``' first
    ``nq + nv`` entries, and the reward summed over its steps (velocity weights: the last ``nv``)."""
    state = torchsim.init(sys, q0, qd0)
    w_final, w_vel = weights[:sys.nq + sys.nv], weights[sys.nq + sys.nv:]
    reward = q0.new_zeros(q0.shape[0])
    for t in range(ctrl.shape[0]):
        state = torchsim.step(sys, state, ctrl[t])
        reward = reward + state.qd @ w_vel - 0.01 * (ctrl[t] ** 2).sum(-1)
    assert not state.diverged.any()
    return torch.cat((state.q, state.qd), -1) @ w_final, reward


def parameter_fields(sys):
    """The differentiated parameters: ``name -> (value, per-env rank)``; the contact groups' friction as
    ``friction``."""
    fields = {"body_mass": 1, "body_inertia": 3}
    if sys.nu:
        fields.update(act_gain=1, act_gear=1)
    if sys.dof_damping.numel():
        fields.update(dof_damping=1, dof_armature=1, dof_stiffness=1)
    out = {name: (getattr(sys, name), rank) for name, rank in fields.items()}
    if sys.contact_groups:
        out["friction"] = (sys.contact_groups[0].friction, 1)
    return out


def with_value(sys, name, value):
    if name == "friction":
        return sys.replace(contact_groups=(sys.contact_groups[0]._replace(friction=value),) + sys.contact_groups[1:])
    return sys.replace(**{name: value})


def autograd(sys, q0, qd0, ctrl, weights, params, sizes):
    """Gradients of both objectives with respect to ``q0, qd0, ctrl``, every parameter of ``params`` and (with
    ``sizes``) the geom sizes: ``{input: (grad final, grad reward)}``."""
    inputs = {"q0": q0.clone().requires_grad_(), "qd0": qd0.clone().requires_grad_(),
              "ctrl": ctrl.clone().requires_grad_()}
    s = sys
    for name in params:
        inputs[name] = params[name][0].clone().requires_grad_()
        s = with_value(s, name, inputs[name])
    if sizes:
        inputs["geom_size"] = sys.geom_size.clone().requires_grad_()
        s = s.replace(geom_size=inputs["geom_size"])
    final, reward = rollout(s, inputs["q0"], inputs["qd0"], inputs["ctrl"], weights)
    grads = [torch.autograd.grad(j.sum(), list(inputs.values()), retain_graph=True, allow_unused=True)
             for j in (final, reward)]
    out = {name: tuple(torch.zeros_like(x) if g[i] is None else g[i] for g in grads)
           for i, (name, x) in enumerate(inputs.items())}
    out.update(q0=tuple(g[0] for g in out["q0"]), qd0=tuple(g[0] for g in out["qd0"]),
               ctrl=tuple(g[:, 0] for g in out["ctrl"]))  # the single env's, as the differences have them
    return out


def finite_differences(sys, q0, qd0, ctrl, weights, params, sizes, eps):
    """Fourth-order central differences ``(8 (J(x + e) - J(x - e)) - (J(x + 2e) - J(x - 2e))) / 12 e`` of both
    objectives with respect to every element of the same inputs, each perturbed by ``e = eps`` times its scale (1
    for the state and controls, a parameter's largest magnitude, or 1 where it is zero). Every perturbation is one
    env of a single batched rollout (the parameters per env). The geom sizes, which are not batchable, are checked
    along one random direction over the geoms ``sizes`` (four rollouts): ``{"geom_size": (direction, dJ)}``."""
    values = {"q0": (q0[0], 1.0), "qd0": (qd0[0], 1.0), "ctrl": (ctrl[:, 0], 1.0)}
    values.update({name: (v, v.abs().max().item() or 1.0) for name, (v, _) in params.items()})
    sizes_of = [v.numel() for v, _ in values.values()]
    n = sum(sizes_of)
    steps = (1, -1, 2, -2)
    batched = {}
    offset = 0
    for (name, (value, scale)), size in zip(values.items(), sizes_of):
        x = value.expand((4 * n,) + value.shape).clone()
        e = torch.eye(size, dtype=F64).view((size,) + value.shape) * eps * scale
        for k, step in enumerate(steps):
            x[k * n + offset:k * n + offset + size] += step * e
        batched[name] = x
        offset += size
    s = sys
    for name in params:
        s = with_value(s, name, batched[name])
    objectives = rollout(s, batched["q0"], batched["qd0"], batched["ctrl"].transpose(0, 1), weights)
    out, offset = {}, 0
    for (name, (value, scale)), size in zip(values.items(), sizes_of):
        out[name] = tuple(stencil(*(j[k * n + offset:k * n + offset + size] for k in range(4)), eps * scale)
                          .view(value.shape) for j in objectives)
        offset += size
    if sizes:
        direction = torch.zeros_like(sys.geom_size)
        direction[list(sizes)] = torch.randn(len(sizes), 3, generator=torch.Generator().manual_seed(2), dtype=F64)
        runs = [rollout(sys.replace(geom_size=sys.geom_size + step * eps * direction), q0, qd0, ctrl, weights)
                for step in steps]
        out["geom_size"] = (direction, tuple(stencil(*(r[i] for r in runs), eps) for i in range(2)))
    return out


def stencil(plus, minus, plus2, minus2, e):
    return (8 * (plus - minus) - (plus2 - minus2)) / (12 * e)


def relative_errors(ad, fd):
    """``max |ad - fd| / max |fd|`` per input and objective (absolute where the derivative is all zero)."""
    if "geom_size" in fd:  # a directional derivative
        direction, derivative = fd.pop("geom_size")
        ad["geom_size"] = tuple((g * direction).sum().reshape(1) for g in ad["geom_size"])
        fd["geom_size"] = tuple(d.reshape(1) for d in derivative)
    return {(name, which): ((a - f).abs().max() / f.abs().max().clamp_min(1.0 if f.abs().max() == 0 else 0)).item()
            for name in fd for which, a, f in zip(("final", "reward"), ad[name], fd[name]) if f.numel()}


def check(sys, q0, qd0, ctrl, eps, sizes=(), bound=1e-6, skip=()):
    eps = float(SWEEP_EPS or eps)
    gen = torch.Generator().manual_seed(1)
    weights = torch.randn(sys.nq + 2 * sys.nv, generator=gen, dtype=F64)
    params = {k: v for k, v in parameter_fields(sys).items() if k not in skip}
    ad = autograd(sys, q0, qd0, ctrl, weights, params, sizes)
    fd = finite_differences(sys, q0, qd0, ctrl, weights, params, sizes, eps)
    errors = relative_errors(ad, fd)
    print(f"max relative error {max(errors.values()):.1e} at {max(errors, key=errors.get)}")
    for key, err in errors.items():
        assert err < bound, (key, err, ad[key[0]], fd[key[0]])
    return ad, errors


@pytest.mark.parametrize("method", ["spring", "xpbd"])
def test_chain_gradients_match_finite_differences(method):
    """Contact-free 3-link chain, 8 steps of 5 ms (5 substeps): state, control and parameter gradients to 1e-6
    relative (max over the input's elements, relative to the largest). Measured max errors (all inputs, both
    objectives) against the step ``e``: spring 3.1e-6 at 1e-3 (truncation), 2.5e-8 at 3e-4, 1.9e-8 at 1e-4,
    1.1e-7 at 1e-5, 1.7e-6 at 1e-6 (rounding, ~1/e); xpbd, whose projection rounds more, 1.1e-6 at 1e-3, 1.0e-7 at
    3e-4, 3.3e-7 at 1e-4, 2.7e-6 at 1e-5."""
    sys = torchsim.load_mjcf(CHAIN, method=method, dtype=F64, substeps=5)
    gen = torch.Generator().manual_seed(0)
    q0 = torch.tensor([[0.3, -0.5, 0.2]], dtype=F64)
    qd0 = torch.tensor([[0.5, 1.0, -0.7]], dtype=F64)
    ctrl = 0.3 * torch.randn(8, 1, sys.nu, generator=gen, dtype=F64)
    ad, _ = check(sys, q0, qd0, ctrl, {"spring": 1e-4, "xpbd": 3e-4}[method])
    assert all(g.abs().max() > 0 for name in ad for g in ad[name])  # every input reaches both objectives


@pytest.mark.parametrize("contact_model", ["impulse", "soft"])
def test_sliding_box_gradients_match_finite_differences(contact_model):
    """A free box sliding and spinning on a plane (1 m/s, friction 0.6: it slips for the whole 0.1 s): the
    gradients with respect to its initial pose and velocity, mass, inertia, friction and size to 1e-6 relative.
    Slipping friction is ``mu j_n`` along the slip, smooth in every input, so the bound is the chain's. Measured:
    2.9e-10 at ``e = 3e-5``, 1.1e-10 at 1e-4; at 3e-4 the stencil (+-2e) crosses a corner's contact switch (4e-2).
    Both contact models: the impulse (default) and MuJoCo's soft normal (``contact_model="soft"``), whose clamped
    impulse (a point that would pull is released) switches within 2e-5 of this start in the box's height (the
    difference at ``e = 1e-5`` is 2e3 against autograd's -3.3), so it takes ``e = 1e-7`` (measured 3.9e-7, bound
    1e-5)."""
    sys = torchsim.load_mjcf(BOX, dtype=F64, substeps=5, contact_model=contact_model)
    q0 = torch.tensor([[0.0, 0.0, 0.0495, 1.0, 0.0, 0.0, 0.0]], dtype=F64)
    qd0 = torch.tensor([[1.0, 0.2, 0.0, 0.0, 0.0, 0.5]], dtype=F64)
    soft = contact_model == "soft"
    ad, _ = check(sys, q0, qd0, q0.new_zeros(10, 1, 0), 1e-7 if soft else 3e-5, sizes=(1,),
                  bound=1e-5 if soft else 1e-6)
    assert ad["friction"][0].abs().max() > 0.1  # the slip distance depends on friction


def test_settling_box_gradients_match_finite_differences():
    """The box set down 0.5 mm deep with a small disturbance (1 cm/s), 5 steps of 10 substeps: it sticks in the
    first substep, rocks on its contacts and settles. Bound 1e-5 relative at ``e = 1e-5`` (measured 5.6e-7):
    sticking friction (``|v_t| / w_t`` below the cap) does not depend on the friction coefficient, so its gradient
    is tiny (2e-5, from the corners that still slip), and rounding on it is ~1e-5 relative at ``e = 1e-6``; at
    ``e = 1e-5`` over 10 steps a corner's stick/slip switch lies inside the stencil (tilt: 2e-3 relative), and
    the differences converge on autograd's value as ``e`` shrinks."""
    sys = torchsim.load_mjcf(BOX, dtype=F64, substeps=10)
    q0 = torch.tensor([[0.0, 0.0, 0.0495, 1.0, 0.0, 0.0, 0.0]], dtype=F64)
    qd0 = torch.tensor([[0.01, 0.002, 0.0, 0.0, 0.0, 0.005]], dtype=F64)
    ad, _ = check(sys, q0, qd0, q0.new_zeros(5, 1, 0), 1e-5, sizes=(1,), bound=1e-5)
    assert ad["friction"][0].abs().max() < 1e-3


def test_resting_box_gradients_along_the_normal():
    """A box at rest, exactly symmetric (no tangential velocity anywhere): the derivatives along the contact normal
    (height, vertical speed, mass, size) match finite differences to 1e-6 relative; friction's are exactly zero.

    Tangential derivatives at exactly zero slip are not defined (the sticking impulse ``-v_t / w_t(v_t / |v_t|)``
    is homogeneous in ``v_t`` but not linear), and autograd's value there, with ``w_t`` along a zero tangent (the
    bare inverse mass), grows 2-5x per step: documented in ``docs/gradients.md``, asserted here as the limitation."""
    sys = torchsim.load_mjcf(BOX, dtype=F64, substeps=5)
    q0 = torch.tensor([[0.0, 0.0, 0.0495, 1.0, 0.0, 0.0, 0.0]], dtype=F64)
    qd0 = torch.zeros(1, 6, dtype=F64)
    gen = torch.Generator().manual_seed(1)
    weights = torch.randn(sys.nq + 2 * sys.nv, generator=gen, dtype=F64)
    params = {k: v for k, v in parameter_fields(sys).items() if k in ("body_mass", "friction")}
    ad = autograd(sys, q0, qd0, q0.new_zeros(10, 1, 0), weights, params, (1,))
    fd = finite_differences(sys, q0, qd0, q0.new_zeros(10, 1, 0), weights, params, (1,), 1e-4)
    direction = fd["geom_size"][0]
    for which in range(2):
        pairs = [(ad["q0"][which][2], fd["q0"][which][2]), (ad["qd0"][which][2], fd["qd0"][which][2]),
                 (ad["body_mass"][which], fd["body_mass"][which]),
                 ((ad["geom_size"][which] * direction).sum(), fd["geom_size"][1][which])]
        for a, f in pairs:
            assert ((a - f).abs() <= 1e-6 * f.abs()).all(), (which, a, f)
        assert ad["friction"][which].abs().max() == 0 and fd["friction"][which].abs().max() == 0
    assert ad["qd0"][0][5].abs() > 1e3  # the undefined tangential derivative (FD: O(1)); see the docstring


def test_pushed_box_control_gradients_match_finite_differences():
    """The planar box pushed along x and twisted about y by motors, sliding on the plane: control, state and
    parameter gradients through the contacts to 1e-6 relative over 10 steps of 5 substeps (it slips throughout).
    Measured 1.1e-7 at ``e = 3e-5``, 8e-9 at 1e-4; at 3e-4 the stencil crosses a contact switch (4e-2)."""
    sys = torchsim.load_mjcf(PUSHED_BOX, dtype=F64, substeps=5)
    gen = torch.Generator().manual_seed(0)
    q0 = torch.tensor([[0.0, -0.0005, 0.0]], dtype=F64)
    qd0 = torch.tensor([[0.5, 0.0, 0.0]], dtype=F64)
    ctrl = torch.tensor([8.0, 0.0], dtype=F64) + torch.tensor([0.5, 0.05], dtype=F64) * torch.randn(
        10, 1, 2, generator=gen, dtype=F64)
    ad, _ = check(sys, q0, qd0, ctrl, 3e-5, sizes=(1,))
    assert ad["ctrl"][0].abs().max() > 0
