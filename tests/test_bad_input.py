"""Wrong inputs and unsupported MJCF fail loudly, with messages that say what is wrong."""

import mujoco
import numpy as np
import pytest
import torch
from tensordict import TensorDict

import torchsim
from models import F64, HUMANOID, PROJECTILE, TWO_HINGES


@pytest.fixture(scope="module")
def humanoid():
    sys = torchsim.load_mjcf(str(HUMANOID), dtype=F64)
    batch = 4
    state = torchsim.init(sys, sys.q0.expand(batch, -1).clone(), torch.zeros(batch, sys.nv, dtype=F64))
    return sys, state, batch


def test_wrong_ctrl_shape(humanoid):
    sys, state, batch = humanoid
    with pytest.raises(ValueError, match="ctrl") as err:
        torchsim.step(sys, state, torch.zeros(batch, sys.nu + 1, dtype=F64))
    assert f"({batch}, {sys.nu})" in str(err.value)  # the expected shape
    assert f"({batch}, {sys.nu + 1})" in str(err.value)  # and what was given
    with pytest.raises(ValueError, match="ctrl"):  # batch size must match the state
        torchsim.step(sys, state, torch.zeros(batch + 1, sys.nu, dtype=F64))


def test_wrong_ctrl_dtype(humanoid):
    sys, state, batch = humanoid
    with pytest.raises(ValueError) as err:
        torchsim.step(sys, state, torch.zeros(batch, sys.nu, dtype=torch.float32))
    assert "torch.float32" in str(err.value) and "torch.float64" in str(err.value)


def test_wrong_q_width(humanoid):
    sys, _, batch = humanoid
    with pytest.raises(ValueError, match=r"\bq\b") as err:
        torchsim.init(sys, torch.zeros(batch, sys.nq - 1, dtype=F64), torch.zeros(batch, sys.nv, dtype=F64))
    assert str(sys.nq) in str(err.value)
    with pytest.raises(ValueError, match="qd"):
        torchsim.init(sys, sys.q0.expand(batch, -1).clone(), torch.zeros(batch, sys.nv + 2, dtype=F64))


def test_missing_file(tmp_path):
    path = tmp_path / "no_such_model.xml"
    with pytest.raises(FileNotFoundError) as err:
        torchsim.load_mjcf(str(path))
    assert str(path) in str(err.value)


def test_spatial_tendon_wrapping_unsupported():
    xml = TWO_HINGES.format(extra="""<worldbody><site name="a" pos="0 0 2"/><site name="b" pos="0 0 3"/>
        <geom name="wheel" type="sphere" size=".1" pos="0 .05 2.5" contype="0" conaffinity="0"/></worldbody>
        <tendon><spatial name="cable"><site site="a"/><geom geom="wheel"/><site site="b"/></spatial></tendon>""")
    mujoco.MjModel.from_xml_string(xml)  # valid MJCF: the rejection is torchsim's
    with pytest.raises(torchsim.UnsupportedMJCFError, match="tendon 'cable': wrapping around geom 'wheel'"):
        torchsim.load_mjcf(xml)


CYLINDER = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body pos="0 0 1"><freejoint/>
      <geom name="barrel" type="cylinder" size="0.1 0.2" {flags}/>
      <geom type="sphere" size="0.05"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_visual_cylinder_loads():
    xml = CYLINDER.format(flags='contype="0" conaffinity="0"')
    sys = torchsim.load_mjcf(xml, dtype=F64)
    m = mujoco.MjModel.from_xml_string(xml)
    # the visual cylinder still contributes its mass; only the sphere touches the floor
    assert np.isclose(sys.body_mass[0].item(), m.body_mass[1], rtol=1e-12)
    assert sys.num_contact_pairs == 1
    state = torchsim.init(sys, sys.q0[None].clone(), torch.zeros(1, sys.nv, dtype=F64))
    state = torchsim.step(sys, state, torch.zeros(1, 0, dtype=F64))
    assert not state.diverged.any()


def test_unknown_method():
    with pytest.raises(ValueError) as err:
        torchsim.load_mjcf(PROJECTILE, method="rk4")
    msg = str(err.value)
    assert "rk4" in msg and "xpbd" in msg and "spring" in msg


# ---------------------------------------------------------------------------------- envs, URDF and training config
@pytest.fixture
def pendulums():
    """Four inverted-pendulum envs at one and the same state."""
    import torchsim.envs

    env = torchsim.envs.make("inverted_pendulum", num_envs=4, dtype=F64)
    env.reset()
    env.set_state(env.init_q.expand(4, -1) + 0.05, torch.full((4, env.sys.nv), 0.1, dtype=F64))
    return env


def test_non_finite_actions_flag_their_envs(pendulums):
    """+inf, -inf and NaN actions are not clipped into full commands: those envs run with zero control and end as
    diverged envs do (terminated, ``state.diverged``), while the env given a finite action steps as usual."""
    env = pendulums
    action = torch.tensor([[float("inf")], [-float("inf")], [float("nan")], [0.0]], dtype=F64)
    out = env.step(TensorDict(action=action, batch_size=[4]))
    assert out["next", "terminated"].squeeze(-1).tolist() == [True, True, True, False]
    assert env.state.diverged.tolist() == [True, True, True, False]
    assert torch.isfinite(out["next", "observation"]).all()
    for bad in range(3):  # as if given zero control, as env 3 was (0 maps onto the middle of +-3)
        torch.testing.assert_close(env.state.q[bad], env.state.q[3], rtol=0, atol=0)


def test_set_state_refuses_non_finite_values(pendulums):
    env = pendulums
    q, qd = env.state.q.clone(), env.state.qd.clone()
    bad_q = q.clone()
    bad_q[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"set_state: q holds NaN or infinite values \(envs \[2\]\)"):
        env.set_state(bad_q, qd)
    bad_qd = qd.clone()
    bad_qd[0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"qd holds NaN or infinite"):
        env.set_state(q, bad_qd)
    assert torch.equal(env.state.q, q)  # nothing was set


@pytest.mark.parametrize("name, value", [("mass_scale", float("nan")), ("friction_scale", 0.0),
                                         ("actuator_gain_scale", -1.0), ("mass_scale", float("inf")),
                                         ("friction_scale", torch.tensor([1.0, 1.0, 0.0, 1.0], dtype=F64))])
def test_set_physics_refuses_non_positive_scales(pendulums, name, value):
    with pytest.raises(ValueError, match=f"set_physics: {name} must be finite and positive"):
        pendulums.set_physics(**{name: value})


def test_set_physics_accepts_positive_scales(pendulums):
    pendulums.set_physics(mass_scale=torch.tensor([0.5, 1.0, 1.5, 2.0], dtype=F64), friction_scale=0.1)
    assert pendulums.sys.body_mass[3].sum() == 2.0 * pendulums.base_sys.body_mass.sum()


@pytest.mark.parametrize("substeps", [0, -2, 2.5])
def test_substeps_must_be_a_positive_integer(substeps):
    with pytest.raises(ValueError, match=f"substeps must be a positive integer.*got {substeps}"):
        torchsim.load_mjcf(PROJECTILE, substeps=substeps)


def test_env_passes_a_zero_substep_count_on():
    """0 is not read as "the task's default": the env refuses it as the loader does."""
    import torchsim.envs

    with pytest.raises(ValueError, match="substeps must be a positive integer.*got 0"):
        torchsim.envs.make("inverted_pendulum", substeps=0)


ZERO_AXIS_URDF = """<robot name="arm">
  <link name="base"/>
  <link name="upper"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <joint name="shoulder" type="continuous"><parent link="base"/><child link="upper"/><axis xyz="0 0 0"/></joint>
</robot>"""


def test_zero_length_urdf_axis():
    with pytest.raises(torchsim.UnsupportedURDFError, match="joint 'shoulder' has a zero-length <axis"):
        torchsim.load_urdf(ZERO_AXIS_URDF)
    torchsim.load_urdf(ZERO_AXIS_URDF.replace('xyz="0 0 0"', 'xyz="0 0 2"'))  # any length but zero loads


@pytest.mark.parametrize("key", ["checkpoint_every", "print_every"])
def test_zero_iteration_interval_is_refused_before_training(key, tmp_path):
    from hydra import compose, initialize_config_dir

    from torchsim.algos.train import CONFIG_DIR, run

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            "algo=ppo", "env=inverted_pendulum", "algo.num_envs=8", "algo.unroll=2", "algo.minibatches=2",
            "budget.env_steps=16", "video.enabled=false", "logger=''", "compile=false", "threads=1", f"{key}=0"])
    with pytest.raises(ValueError, match=f"{key} must be a positive number of iterations, got 0"):
        run(cfg, tmp_path)
    assert not any(tmp_path.iterdir())  # refused before anything ran


@pytest.mark.parametrize("field,message", [("q", "state.q must be"), ("x_pos", r"ctrl must have shape \(1, ")])
def test_step_kernel_refuses_a_state_whose_fields_disagree_on_batch(field, message):
    """Generated code reads raw memory: a State whose fields hold different batch sizes (``state._replace(q=
    state.q[:1])``) is refused by name before the kernel runs, not read or written out of bounds (the batch is the
    poses': ``x_pos`` cut short makes the controls the misfit)."""
    sys = torchsim.load_mjcf(TWO_HINGES, method="spring", dtype=F64)
    state = torchsim.init(sys, sys.q0.expand(3, -1).clone(), torch.zeros(3, sys.nv, dtype=F64))
    stepper = torchsim.Stepper(sys, "kernel")
    ctrl = torch.zeros(3, sys.nu, dtype=F64)
    stepper(state, ctrl)
    with pytest.raises(ValueError, match=message):
        stepper(state._replace(**{field: getattr(state, field)[:1]}), ctrl)


@pytest.mark.parametrize("argv,message", [
    (["checkpoint=x.pt", "episode=3"], r"'episode=3' is not key=value for one of its keys \(checkpoint, episodes"),
    (["x.pt"], "'x.pt' is not key=value"),
    ([], "give the policy to run, checkpoint="),
])
def test_evaluate_names_a_bad_argument(argv, message):
    """``python -m torchsim.evaluate`` with a misspelt key, a bare path or no checkpoint exits saying which."""
    from torchsim.algos.evaluate import main

    with pytest.raises(SystemExit, match=message):
        main(argv)
