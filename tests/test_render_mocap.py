"""``torchsim.render`` draws mocap bodies where each env's mocap pose puts them, as ``mujoco.Renderer`` does after
``data.mocap_pos``/``mocap_quat`` are set.

A mocap box carries a jointless child (a sphere, fused into the mocap body) and a camera; a free capsule and a floor
are the rest. Each env moves and turns the mocap body differently; MuJoCo renders each env from a model whose mocap
body sits at that env's pose (its ``mocap_pos``/``mocap_quat`` at ``mj_forward`` are the model's; the models' extent
is fixed, which sets the clip distances and so the empty pixels' depth), through
``test_render``'s child-process reference renderer and its agreement criteria (depth within 1 cm or 0.5%, same geom,
on 99% of pixels). The moved geoms must be in view, and the model's pose must not pass for them.
"""

import mujoco
import numpy as np
import pytest
import torch

import torchsim
from test_render import fmt, mujoco_images, xyaxes
from torchsim.render import Camera, Scene, render

H, W = 48, 48
XML = """<mujoco><statistic extent="2" center="0 0 0.3"/><worldbody>
  <geom name="floor" type="plane" size="3 3 0.1" rgba="0.8 0.9 0.8 1"/>
  <camera name="top" pos="{eye}" xyaxes="{xyaxes}" fovy="50"/>
  <body name="rod" pos="-0.4 0.3 0.3"><freejoint/><geom name="rod" type="capsule" size="0.05 0.2" euler="0 90 0"/>
  </body>
  <body name="target" mocap="true" pos="{pos}" quat="{quat}">
    <geom name="box" type="box" size="0.3 0.2 0.2" rgba="0.9 0.2 0.2 1" contype="0" conaffinity="0"/>
    <camera name="carried" pos="0 -1.2 0.6" xyaxes="1 0 0 0 0.45 0.9" fovy="60"/>
    <body name="knob" pos="0.35 0 0.25" euler="0 30 0">
      <geom name="knob" type="sphere" pos="0.05 0 0" size="0.12" rgba="0.2 0.2 0.9 1" contype="0" conaffinity="0"/>
    </body>
  </body>
</worldbody></mujoco>"""
EYE, LOOK = (1.0, -1.2, 1.1), (0.0, 0.0, 0.2)
MODEL_POSE = ((0.0, 0.0, 0.3), (0.0, 0.0, 0.0))  # position [m], xyz euler [deg]
ENV_POSES = [((0.5, 0.2, 0.35), (0, 0, 40)), ((-0.3, -0.4, 0.5), (30, 0, -20)), ((0.2, 0.5, 0.25), (0, 50, 90))]


def _xml(pos, euler):
    quat = np.zeros(4)
    mujoco.mju_euler2Quat(quat, np.radians(euler), "xyz")
    return XML.format(eye=fmt(EYE), xyaxes=fmt(xyaxes(EYE, LOOK)), pos=fmt(pos), quat=fmt(quat)), quat


@pytest.fixture(scope="module")
def images():
    """torchsim's depth and segmentation ``(B, 2, H, W)`` with per-env mocap poses and with the model's, MuJoCo's
    per env, and the scene."""
    xml, _ = _xml(*MODEL_POSE)
    system = torchsim.load_mjcf(xml)
    scene = Scene.build(xml, system)
    batch = len(ENV_POSES)
    state = torchsim.init(system, system.q0.expand(batch, -1).clone(), torch.zeros(batch, system.nv))
    env_xmls = [_xml(pos, euler) for pos, euler in ENV_POSES]
    mocap_pos = torch.tensor([[pos] for pos, _ in ENV_POSES], dtype=system.dtype)
    mocap_quat = torch.tensor(np.array([[quat] for _, quat in env_xmls]), dtype=system.dtype)
    cams = ["top", "carried"]
    moved = render(scene, state, cams, H, W, mocap_pos=mocap_pos, mocap_quat=mocap_quat)
    at_model = render(scene, state, cams, H, W)
    refs = mujoco_images([(x, state.q[:1].double().numpy(), tuple(cams), H, W) for x, _ in env_xmls])
    depth_ref = np.concatenate([d for d, _ in refs])
    seg_ref = np.concatenate([s for _, s in refs])
    return moved, at_model, (depth_ref, seg_ref), scene


def _agreement(ours, depth_ref, seg_ref):
    """Fractions of pixels per camera whose depth and whose geom agree with MuJoCo's (test_render's criteria)."""
    close = np.abs(ours.depth.numpy() - depth_ref) <= np.maximum(0.01, 0.005 * depth_ref)
    same = ours.segmentation.numpy() == seg_ref
    return close.mean((0, 2, 3)), same.mean((0, 2, 3))


def test_mocap_geoms_drawn_at_each_envs_mocap_pose(images):
    """Both cameras (a world one and one carried by the mocap body) agree with MuJoCo per env (measured: depth on
    99.96% and 99.97% of pixels, geom on 99.99% and 99.97%); drawn at the model's pose instead, as before the mocap
    frames, they agree on 76% and 31% (depth), 78% and 71% (geom)."""
    moved, at_model, (depth_ref, seg_ref), scene = images
    model = mujoco.MjModel.from_xml_string(_xml(*MODEL_POSE)[0])
    mocap_geoms = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("box", "knob")]
    # the mocap geoms are well in view (12% of the pixels) in MuJoCo's images from both cameras, and differently placed per env
    for c in range(2):
        assert np.isin(seg_ref[:, c], mocap_geoms).mean() > 0.05
    assert not np.array_equal(seg_ref[0, 0], seg_ref[1, 0])
    depth_ok, seg_ok = _agreement(moved, depth_ref, seg_ref)
    assert (depth_ok >= 0.99).all() and (seg_ok >= 0.99).all(), (depth_ok, seg_ok)
    # the model's pose for every env is far off: the test sees where the mocap geoms are drawn
    depth_off, seg_off = _agreement(at_model, depth_ref, seg_ref)
    assert (depth_off < 0.95).all() and (seg_off < 0.95).all(), (depth_off, seg_off)


def test_default_and_shared_mocap_poses():
    """Without mocap poses the model's are drawn, the same as passing them; a shared ``(K, 3)`` pose is every
    env's; a wrong shape is refused naming the expected ones; ``Camera.look_at``'s world camera (``-1``) stays on
    the world, not on the last mocap frame."""
    xml, quat = _xml(*MODEL_POSE)
    system = torchsim.load_mjcf(xml)
    scene = Scene.build(xml, system)
    assert scene.num_mocap == 1 and torch.allclose(scene.mocap_pos, torch.tensor([MODEL_POSE[0]], dtype=torch.float64))
    state = torchsim.init(system, system.q0.expand(2, -1).clone(), torch.zeros(2, system.nv))
    look = Camera.look_at(EYE, LOOK, fovy=50)
    default = render(scene, state, look, H, W)
    explicit = render(scene, state, look, H, W, mocap_pos=torch.tensor([MODEL_POSE[0]]),
                      mocap_quat=torch.tensor(np.array([quat])))
    assert torch.equal(default.segmentation, explicit.segmentation)
    assert torch.allclose(default.depth, explicit.depth, atol=1e-6)
    top = render(scene, state, "top", H, W)  # the same pose as the MJCF camera "top"
    assert (default.segmentation == top.segmentation).float().mean() > 0.99
    shared = render(scene, state, look, H, W, mocap_pos=torch.tensor([ENV_POSES[0][0]]))
    assert torch.equal(shared.segmentation[0], shared.segmentation[1])
    assert not torch.equal(shared.segmentation[0], default.segmentation[0])
    with pytest.raises(ValueError, match=r"mocap_pos must be \(1, 3\) or \(2, 1, 3\)"):
        render(scene, state, look, H, W, mocap_pos=torch.zeros(3, 1, 3))


def test_viewer_puts_mocap_geoms_on_the_mocap_frame():
    """The viewer's mocap geoms are children of a frame at the mocap body's model pose, placed in it as the scene
    holds them (relative to the mocap body), not at those relative poses in the world."""
    pytest.importorskip("viser", reason="viser not installed (pip install viser)")
    from torchsim.render.viewer import Viewer

    xml, quat = _xml((0.4, -0.2, 0.5), (0, 0, 60))
    system = torchsim.load_mjcf(xml)
    scene = Scene.build(xml, system)
    box = scene.geom_id.tolist().index(mujoco.mj_name2id(mujoco.MjModel.from_xml_string(xml),
                                                         mujoco.mjtObj.mjOBJ_GEOM, "box"))
    assert int(scene.geom_body[box]) == system.num_bodies + 1  # the first mocap frame
    assert torch.allclose(scene.geom_pos[box], torch.zeros(3, dtype=torch.float64), atol=1e-12)
    viewer = Viewer(scene, host="127.0.0.1", port=8791, verbose=False)
    try:
        np.testing.assert_allclose(viewer.mocap[0].position, (0.4, -0.2, 0.5), atol=1e-9)
        np.testing.assert_allclose(np.abs(viewer.mocap[0].wxyz @ quat), 1.0, atol=1e-9)
    finally:
        viewer.close()
