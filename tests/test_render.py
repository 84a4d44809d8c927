"""torchsim.render against closed forms and against MuJoCo's own renderer.

The MuJoCo reference images come from ``mujoco.Renderer`` (depth and segmentation rendering) in a child process
with ``MUJOCO_GL=egl`` (``osmesa`` as a fallback): MuJoCo picks its GL backend when it is first imported, which in a
test session has already happened. Agreement criteria: a pixel's depth agrees when within 1 cm or 0.5% of
MuJoCo's; at least 99% of pixels must agree, and at least 99% must see the same geom. The residue is where MuJoCo's
tessellated spheres and capsules (``vis.quality``) and our exact surfaces disagree on which geom a silhouette pixel
sees. Errors fail it (checked by breaking the code on purpose): rays shifted by half a pixel sideways fail every model
(95.5-98.8% agreement), track cameras turned with their body 12-79%, geom offsets not turned into a fused body's
frame 98.5% (the ``fused`` model).
"""

import os
import pickle
import subprocess
import sys
import tempfile
import warnings
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import torch

import torchsim
import torchsim.envs
from torchsim.io_urdf import urdf_to_mjcf
from torchsim.render import Camera, Scene, UnsupportedGeomError, render

H, W = 64, 64
STATES = 3

# --------------------------------------------------------------------------------------------- the MuJoCo side
REFERENCE = r"""
import os, pickle, sys
os.environ["MUJOCO_GL"] = sys.argv[3]
import mujoco, numpy as np
cases = pickle.load(open(sys.argv[1], "rb"))
out = []
for xml, qpos, cams, h, w in cases:
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    r = mujoco.Renderer(m, h, w)
    depth = np.zeros((len(qpos), len(cams), h, w), np.float32)
    seg = np.zeros((len(qpos), len(cams), h, w), np.int64)
    for s, q in enumerate(qpos):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        for c, cam in enumerate(cams):
            r.enable_depth_rendering(); r.update_scene(d, cam); depth[s, c] = r.render(); r.disable_depth_rendering()
            r.enable_segmentation_rendering(); r.update_scene(d, cam); ids = r.render()
            r.disable_segmentation_rendering()
            seg[s, c] = np.where(ids[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), ids[..., 0], -1)
    r.close()
    out.append((depth, seg))
pickle.dump(out, open(sys.argv[2], "wb"))
"""


def mujoco_images(cases):
    """MuJoCo's depth and segmentation images ``(S, C, H, W)`` for each case ``(xml, qpos (S, nq), cameras, h, w)``,
    rendered in a child process; skips (naming the errors) only where no off-screen GL context can be made."""
    errors = []
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.pkl"), os.path.join(tmp, "out.pkl")
        with open(src, "wb") as f:
            pickle.dump(cases, f)
        for backend in ("egl", "osmesa"):
            run = subprocess.run([sys.executable, "-c", REFERENCE, src, dst, backend], capture_output=True, text=True,
                                 timeout=300)
            if run.returncode == 0:
                with open(dst, "rb") as f:
                    return pickle.load(f)
            errors.append((backend, run.stderr))
    gl_words = ("egl", "osmesa", "opengl", "gl context", "glad", "libgl")
    gl_only = all(any(word in err.lower() for word in gl_words) for _, err in errors)
    errors = [f"{backend}: {err.strip().splitlines()[-1] if err.strip() else 'failed'}" for backend, err in errors]
    if gl_only:
        pytest.skip("MuJoCo's renderer has no off-screen GL context here: " + "; ".join(errors))
    raise RuntimeError("MuJoCo reference rendering failed: " + "; ".join(errors))


# ----------------------------------------------------------------------------------------- models and cameras
def xyaxes(eye, target, up=(0.0, 0.0, 1.0)):
    """MuJoCo ``xyaxes`` of a camera at ``eye`` looking at ``target`` (the camera looks along its -z)."""
    z = np.asarray(eye, float) - np.asarray(target, float)
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return np.concatenate((x, np.cross(z, x)))


def fmt(v):
    return " ".join(f"{float(x):.9g}" for x in v)


#: Per model: a world camera (eye, target), and a camera carried by a body (body, eye, target in world
#: coordinates at the reference pose), added once as ``mode="fixed"`` and once as ``mode="track"``.
VIEWS = {
    "ant": (((1.8, -1.8, 1.5), (0.0, 0.0, 0.4)), ("torso", (0.5, -2.5, 1.5), (0.0, 0.0, 0.5))),
    "reacher": (((0.12, -0.2, 0.22), (0.06, 0.0, 0.0)), ("body1", (0.05, -0.25, 0.2), (0.12, 0.0, 0.0))),
    "grasp": (((12.0, -12.0, 10.0), (0.0, 0.0, 3.0)), ("palm", (1.0, -10.0, 6.0), (0.0, 0.0, 3.0))),
    "ur5e_reach": (((1.1, -1.1, 1.0), (0.0, 0.0, 0.4)), ("forearm_link", (0.9, -1.2, 1.0), (0.1, -0.3, 0.5))),
    "pusher": (((1.2, -1.8, 1.0), (0.3, -0.3, -0.2)), ("r_forearm_link", (0.6, -1.4, 0.5), (0.6, -0.5, -0.1))),
    "fetch": (((6.0, -6.0, 5.0), (0.0, 0.0, 1.0)), ("torso", (2.0, -6.0, 3.0), (0.0, 0.0, 1.0))),
    "fused": (((2.2, -2.2, 2.0), (0.6, 0.3, 0.8)), ("tip", (1.2, -1.2, 1.6), (0.7, 0.1, 1.0))),
}


#: Jointless bodies (fused into their parent by torchsim) turned and offset, carrying geoms and a camera;
#: visual-only geoms (contype = conaffinity = 0) on jointed and fused bodies; a free box.
FUSED_XML = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="5 5 0.1" rgba="0.8 0.9 0.8 1"/>
  <body name="arm" pos="0 0 1"><joint name="h1" type="hinge" axis="0 1 0"/>
    <geom name="upper" type="capsule" fromto="0 0 0 0.6 0 0" size="0.08"/>
    <body name="bracket" pos="0.6 0 0" euler="0 30 45">
      <geom name="plate" type="box" pos="0.2 0.1 0" size="0.15 0.05 0.1" rgba="0.8 0.2 0.2 1"/>
      <geom name="knob" type="cylinder" pos="0 0.2 0.1" euler="90 0 0" size="0.06 0.1" contype="0" conaffinity="0"/>
      <body name="hand" pos="0.3 0 0"><joint name="h2" type="hinge" axis="0 0 1"/>
        <geom name="palm" type="ellipsoid" pos="0.15 0 0" size="0.15 0.08 0.05" contype="0" conaffinity="0"/>
        <body name="tip" pos="0.3 0 0" euler="20 0 0">
          <geom name="nail" type="sphere" pos="0 0.05 0" size="0.07"/></body>
      </body>
    </body>
  </body>
  <body name="block" pos="1 1 0.5"><freejoint/><geom name="cube" type="box" size="0.2 0.2 0.2"/></body>
</worldbody></mujoco>"""


def model_xml(name: str, fine: bool = False) -> str:
    """The env's simulated MJCF (as the env builds it), with the test's cameras added; ``fine``: with MuJoCo's
    renderer tessellating round shapes finely (``<visual><quality numslices numstacks>``; not physics)."""
    if name == "ur5e_reach":
        from torchsim.envs import ur5e
        urdf = urdf_to_mjcf(torchsim.envs.asset_path("ur5e.urdf"), armature=ur5e.UR5eReach.urdf_armature)
        xml = ur5e.servo_model(urdf, ur5e.SERVO_KP, ur5e.SERVO_KD, ur5e.HOME)
    elif name == "fused":
        xml = FUSED_XML
    else:
        xml = torchsim.envs.asset_path(f"{name}.xml").read_text()
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qpos[:] = reference_q(m)
    mujoco.mj_forward(m, d)
    (eye, target), (body, beye, btarget) = VIEWS[name]
    root = ET.fromstring(xml)
    ET.SubElement(root.find("worldbody"), "camera", name="world", pos=fmt(eye), xyaxes=fmt(xyaxes(eye, target)),
                  fovy="50")
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)
    rot = d.xmat[b].reshape(3, 3)
    axes = xyaxes(beye, btarget).reshape(2, 3)
    element = next(e for e in root.iter("body") if e.get("name") == body)
    ET.SubElement(element, "camera", name="fixed", pos=fmt(rot.T @ (np.asarray(beye) - d.xpos[b])),
                  xyaxes=fmt((axes @ rot).ravel()), fovy="45")
    ET.SubElement(element, "camera", name="track", mode="track", pos=fmt(rot.T @ (np.asarray(beye) - d.xpos[b])),
                  xyaxes=fmt((axes @ rot).ravel()), fovy="60")
    if fine:
        visual = root.find("visual") if root.find("visual") is not None else ET.SubElement(root, "visual")
        ET.SubElement(visual, "quality", numslices="200", numstacks="100")
    return ET.tostring(root, encoding="unicode")


def reference_q(m):
    return m.key_qpos[0].copy() if m.nkey else m.qpos0.copy()


def random_q(m, count, seed):
    """``count`` random poses around the reference pose: hinges +-0.6 rad, slides +-5% of the model's extent,
    free bodies moved +-0.2 m and turned up to ~0.5 rad (geoms may interpenetrate: both renderers draw them)."""
    rng = np.random.default_rng(seed)
    q = np.tile(reference_q(m), (count, 1))
    for j in range(m.njnt):
        a, kind = m.jnt_qposadr[j], m.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_HINGE:
            q[:, a] += rng.uniform(-0.6, 0.6, count)
        elif kind == mujoco.mjtJoint.mjJNT_SLIDE:
            q[:, a] += rng.uniform(-0.05, 0.05, count) * m.stat.extent
        elif kind == mujoco.mjtJoint.mjJNT_FREE:
            q[:, a:a + 3] += rng.uniform(-0.2, 0.2, (count, 3))
            quat = q[:, a + 3:a + 7] + rng.uniform(-0.25, 0.25, (count, 4))
            q[:, a + 3:a + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    return q


MODELS = ("ant", "reacher", "ur5e_reach", "grasp", "pusher", "fetch", "fused")
CAMERAS = ("world", "fixed", "track")


@pytest.fixture(scope="module")
def agreement():
    return compare_with_mujoco()


def compare_with_mujoco(models=MODELS, cameras=CAMERAS, states=STATES, h=H, w=W, fine=False):
    """Per model: ((torchsim images, scene, state, system), (MuJoCo depth, MuJoCo segmentation)) at ``states``
    random states."""
    cases, ours = [], {}
    for i, name in enumerate(models):
        xml = model_xml(name, fine)
        m = mujoco.MjModel.from_xml_string(xml)
        with warnings.catch_warnings():  # the UR5e's full-turn hinges (a physics caveat, not a rendering one)
            warnings.filterwarnings("ignore", message="hinges .* ranges wider than a turn")
            system = torchsim.load_mjcf(xml)
        scene = Scene.build(m, system)
        q = torch.as_tensor(random_q(m, states, seed=i), dtype=system.dtype)
        state = torchsim.init(system, q, torch.zeros(states, system.nv, dtype=system.dtype))
        ours[name] = (render(scene, state, list(cameras), h, w), scene, state, system)
        cases.append((xml, state.q.double().numpy(), tuple(cameras), h, w))  # MuJoCo at torchsim's q
    return {name: (ours[name], ref) for name, ref in zip(models, mujoco_images(cases))}


@pytest.mark.parametrize("name", MODELS)
def test_agrees_with_mujoco_renderer(agreement, name):
    (images, scene, _, _), (depth_ref, seg_ref) = agreement[name]
    depth, seg = images.depth.numpy(), images.segmentation.numpy()
    assert depth.shape == depth_ref.shape == (STATES, len(CAMERAS), H, W)
    close = np.abs(depth - depth_ref) <= np.maximum(0.01, 0.005 * depth_ref)
    same = seg == seg_ref
    for c, cam in enumerate(CAMERAS):
        seen = (seg_ref[:, c] >= 0).mean()
        assert seen > 0.2, f"{name}/{cam}: the camera sees too little to test anything ({seen:.0%} of pixels)"
        assert close[:, c].mean() >= 0.99, f"{name}/{cam}: depth agrees on {close[:, c].mean():.2%} of pixels"
        assert same[:, c].mean() >= 0.99, f"{name}/{cam}: segmentation agrees on {same[:, c].mean():.2%} of pixels"
    # the moving bodies are in view: the test is about them, not the floor
    moving = scene.geom_id[scene.geom_body < scene.num_bodies].numpy()
    for c, cam in enumerate(CAMERAS):
        assert np.isin(seg_ref[:, c], moving).mean() > 0.03, f"{name}/{cam}: the moving bodies are hardly in view"


@pytest.fixture(scope="module")
def fine_agreement():
    return compare_with_mujoco(fine=True)


@pytest.mark.parametrize("name", MODELS)
def test_agrees_closely_with_finely_tessellated_mujoco(fine_agreement, name):
    """With MuJoCo's round shapes tessellated finely, the residue shrinks to overlapping geoms' ties: a stricter
    test of the camera convention and body mapping (measured: depth >= 99.98%, segmentation >= 99.77% per
    camera; p99 depth error <= 0.6 mm)."""
    (images, _, _, _), (depth_ref, seg_ref) = fine_agreement[name]
    depth, seg = images.depth.numpy(), images.segmentation.numpy()
    close = np.abs(depth - depth_ref) <= np.maximum(0.01, 0.005 * depth_ref)
    for c, cam in enumerate(CAMERAS):
        assert close[:, c].mean() >= 0.999, f"{name}/{cam}: depth agrees on {close[:, c].mean():.2%} of pixels"
        same = (seg[:, c] == seg_ref[:, c]).mean()
        assert same >= 0.997, f"{name}/{cam}: segmentation agrees on {same:.2%} of pixels"


@pytest.mark.parametrize("name", ("ant", "grasp", "pusher", "fetch"))
def test_tile_culling_changes_nothing(agreement, name):
    """Culling by screen tiles (the default) gives the images of testing every pixel against every geom, for tile
    sizes that do and do not divide the image."""
    (images, scene, state, _), _ = agreement[name]
    dense = render(scene, state, list(CAMERAS), H, W, rgb=True, tile=0)
    assert torch.equal(images.depth, dense.depth) and torch.equal(images.segmentation, dense.segmentation)
    odd = render(scene, state, list(CAMERAS), H, W, rgb=True, tile=5)
    for a, b in zip(dense, odd):
        assert torch.equal(a, b)


def test_cameras_made_in_code_match_the_mjcf_cameras(agreement):
    """Cameras made in code (``look_at``, ``on_body``) see what the same MJCF cameras see."""
    (images, scene, state, _), _ = agreement["ant"]
    (eye, target), _ = VIEWS["ant"]
    ours = render(scene, state, Camera.look_at(eye, target, fovy=50.0), H, W)
    assert ours.depth.shape == (STATES, H, W)
    torch.testing.assert_close(ours.depth, images.depth[:, 0], atol=1e-4, rtol=1e-5)
    assert (ours.segmentation == images.segmentation[:, 0]).double().mean() > 0.998  # float32 rounding at edges
    # a camera put on a (fused) body in code sees what the MJCF camera on that body sees
    (images, scene, state, _), _ = agreement["fused"]
    m = mujoco.MjModel.from_xml_string(model_xml("fused"))
    c = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "fixed")
    cam = Camera.on_body(scene, "tip", m.cam_pos[c], m.cam_quat[c], fovy=float(m.cam_fovy[c]))
    ours = render(scene, state, cam, H, W)
    torch.testing.assert_close(ours.depth, images.depth[:, 1], atol=1e-4, rtol=1e-5)
    assert (ours.segmentation == images.segmentation[:, 1]).double().mean() > 0.998


# ------------------------------------------------------------------------------------------------ closed forms
SHAPES_XML = """<mujoco><asset><mesh name="tet" vertex="0 0 0 1 0 0 0 1 0 0 0 1"/></asset><worldbody>
  <geom name="floor" type="plane" size="0 0 1" rgba="0.2 0.4 0.6 1"/>
  <geom name="ball" type="sphere" pos="0 0 1" size="0.5" rgba="1 0.5 0 1"/>
  <geom name="crate" type="box" pos="10 0 1" size="0.3 0.4 0.7" euler="0 0 30"/>
  <geom name="pill" type="capsule" pos="20 0 1" size="0.2 0.6"/>
  <geom name="can" type="cylinder" pos="30 0 1" size="0.4 0.3"/>
  <geom name="egg" type="ellipsoid" pos="40 0 1" size="0.3 0.2 0.6"/>
  <geom name="hidden" type="sphere" pos="0 0 2" size="0.2" group="3"/>
  <geom name="clear" type="sphere" pos="0 0 2" size="0.2" rgba="1 1 1 0"/>
  <body name="b" pos="50 0 1"><freejoint/><geom name="mover" type="sphere" size="0.25"/>
    <geom name="tetra" type="mesh" mesh="tet" pos="0 0 -1.5" contype="0" conaffinity="0"/></body>
</worldbody></mujoco>"""
#: Exact depth at the centre of the image of a camera 5 m above each geom's centre (z = 1), looking down.
TOP_DEPTH = {"floor": 6.0, "ball": 4.5, "crate": 4.3, "pill": 4.2, "can": 4.7, "egg": 4.4}


def shapes_scene(**kw):
    system = torchsim.load_mjcf(SHAPES_XML, dtype=torch.float64)
    state = torchsim.init(system, system.q0[None], torch.zeros(1, system.nv, dtype=torch.float64))
    return Scene.build(mujoco.MjModel.from_xml_string(SHAPES_XML), system, **kw), state


def test_unsupported_geom_is_named():
    """A signed-distance-field geom (MuJoCo's torus plugin; not drawn; ``torchsim.load_mjcf`` does not load it, so
    the scene is built from the model with one added to the world against the system without it: same bodies)."""
    torus = ('<extension><plugin plugin="mujoco.sdf.torus"><instance name="torus"><config key="radius1" value="0.35"/>'
             '<config key="radius2" value="0.15"/></instance></plugin></extension>')
    xml = SHAPES_XML.replace("<mujoco>", "<mujoco>" + torus).replace(
        "<asset>", '<asset><mesh name="torus"><plugin instance="torus"/></mesh>').replace(
        "<worldbody>", '<worldbody><geom name="ring" type="sdf" mesh="torus" pos="0 0 -3"><plugin instance="torus"/>'
        '</geom>')
    system = torchsim.load_mjcf(SHAPES_XML)
    with pytest.raises(UnsupportedGeomError, match="'ring'.*SDF"):
        Scene.build(mujoco.MjModel.from_xml_string(xml), system)
    scene = Scene.build(mujoco.MjModel.from_xml_string(xml), system, skip_unsupported=True)
    assert scene.skipped == ("ring",) and "mesh" in scene.geom_type  # the tetrahedron is drawn


def test_closed_form_depths():
    scene, state = shapes_scene(skip_unsupported=True)
    m = mujoco.MjModel.from_xml_string(SHAPES_XML)
    ids = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("hidden", "clear", "mover")}
    assert ids["hidden"] not in scene.geom_id and ids["clear"] not in scene.geom_id  # group 3, transparent: not drawn
    assert ids["mover"] in scene.geom_id and scene.num_geoms == 8  # the tetrahedron below the mover too
    xs = {"floor": -5.0, "ball": 0.0, "crate": 10.0, "pill": 20.0, "can": 30.0, "egg": 40.0}
    cams = [Camera.look_at((x, 0.0, 6.0), (x, 0.0, 0.0), up=(0.0, 1.0, 0.0), fovy=30.0) for x in xs.values()]
    images = render(scene, state, cams, 31, 41, rgb=True)
    centre = images.depth[0, :, 15, 20]
    torch.testing.assert_close(centre, torch.tensor(list(TOP_DEPTH.values()), dtype=torch.float64), atol=1e-9, rtol=0)
    names = ["floor", "ball", "crate", "pill", "can", "egg"]
    assert images.segmentation[0, :, 15, 20].tolist() == [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
                                                          for n in names]
    # the sphere, every pixel: |t (X, Y, -1) - (0, 0, -5)| = 0.5 solved for the planar depth t
    half = np.tan(np.radians(15.0))
    x = (2 * (np.arange(41) + 0.5) / 41 - 1) * half * 41 / 31
    y = (1 - 2 * (np.arange(31) + 0.5) / 31) * half
    a = x[None, :] ** 2 + y[:, None] ** 2 + 1
    disc = 5.0 ** 2 - a * (5.0 ** 2 - 0.25)
    expect = np.where(disc >= 0, (5.0 - np.sqrt(np.clip(disc, 0, None))) / a, np.inf)
    ball = images.depth[0, 1].numpy()
    on = np.isfinite(expect)
    assert 50 < on.sum() < 31 * 41
    np.testing.assert_allclose(ball[on], expect[on], atol=1e-9)
    assert (ball[~on] > 5.0).all()  # the floor, 6 m down (less towards the corners: planar depth)
    # RGB: each geom's top faces the camera (Lambert factor ambient + diffuse = 1): its own colour
    colours = [[0.2, 0.4, 0.6], [1.0, 0.5, 0.0]] + [[0.5, 0.5, 0.5]] * 4
    torch.testing.assert_close(images.rgb[0, :, 15, 20], torch.tensor(colours, dtype=torch.float64))
    # and over the ball, 0.3 + 0.7 |cos| of the angle between the ray and the sphere's normal at the hit
    rays = np.stack(np.broadcast_arrays(x[None, :], y[:, None], -np.ones((31, 1))), -1)
    hit = np.where(on, expect, 1.0)[..., None] * rays
    normal = (hit - np.array([0.0, 0.0, -5.0])) / 0.5
    cos = np.abs((normal * hit).sum(-1)) / np.linalg.norm(hit, axis=-1)
    shade = images.rgb[0, 1].numpy()[on] / np.array([1.0, 0.5, 0.0]).clip(1e-9)
    np.testing.assert_allclose(shade[:, 0], (0.3 + 0.7 * cos)[on], atol=1e-6)


def test_background_clip_and_chunking():
    scene, state = shapes_scene(skip_unsupported=True)
    cam = Camera.look_at((0.0, -3.0, 1.0), (0.0, 0.0, 1.0), fovy=60.0)  # the floor's horizon splits the image
    full = render(scene, state.__class__(*(x.expand(5, *x.shape[1:]) for x in state)), cam, 24, 32, rgb=True)
    assert full.depth.shape == (5, 24, 32) and full.rgb.shape == (5, 24, 32, 3)
    sky = full.segmentation[0] == -1
    assert sky[:8].all() and not sky[-8:].any()
    assert (full.depth[0][sky] == scene.zfar).all() and (full.rgb[0][sky] == 0).all()
    chunked = render(scene, state.__class__(*(x.expand(5, *x.shape[1:]) for x in state)), cam, 24, 32, rgb=True,
                     max_tests=1)  # one env at a time
    for a, b in zip(full, chunked):
        assert torch.equal(a, b)


def test_compiled_hit_tests_match_eager():
    """``compile=True`` (the hit tests through torch.compile) and ``torch.compile(render)`` give the eager images
    to float rounding."""
    xml = SHAPES_XML.split("<geom name=\"pill\"")[0] + "</worldbody></mujoco>"  # plane, sphere, box only
    system = torchsim.load_mjcf(xml)
    scene = Scene.build(mujoco.MjModel.from_xml_string(xml), system)
    state = torchsim.init(system, system.q0[None], torch.zeros(1, system.nv))
    cams = [Camera.look_at((3.0, -6.0, 4.0), (5.0, 0.0, 1.0)), Camera.look_at((0.0, -3.0, 1.0), (0.0, 0.0, 1.0))]
    eager, compiled = (render(scene, state, cams, 40, 48, compile=c) for c in (False, True))
    torch.testing.assert_close(compiled.depth, eager.depth, rtol=1e-5, atol=1e-5)
    assert (compiled.segmentation == eager.segmentation).double().mean() > 0.999
    assert (eager.segmentation >= 0).double().mean() > 0.5
    # and the whole dense render (tile=0: no data-dependent shapes) through torch.compile
    whole = torch.compile(lambda s: render(scene, s, cams, 40, 48, tile=0))(state)
    torch.testing.assert_close(whole.depth, eager.depth, rtol=1e-5, atol=1e-5)
    assert (whole.segmentation == eager.segmentation).double().mean() > 0.999


def test_body_pose_moves_the_geoms():
    """A geom on a free body follows ``State.x_pos``/``x_quat``; float32 and float64 agree."""
    scene, state = shapes_scene(skip_unsupported=True)
    cam = Camera.look_at((50.0, 0.0, 6.0), (50.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fovy=30.0)
    moved = state._replace(x_pos=state.x_pos + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    d0, d1 = render(scene, state, cam, 31, 31).depth, render(scene, moved, cam, 31, 31).depth
    assert d0[0, 15, 15].item() == pytest.approx(4.75) and d1[0, 15, 15].item() == pytest.approx(3.75)
    single = render(scene, state._replace(x_pos=state.x_pos.float(), x_quat=state.x_quat.float()), cam, 31, 31)
    assert single.depth.dtype == torch.float32
    torch.testing.assert_close(single.depth.double(), d0, atol=1e-5, rtol=1e-6)
