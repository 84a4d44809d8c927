"""The Brax-suite env models in envs/assets: they load (spring and xpbd), enumerate the intended contact pairs, pose
like MuJoCo, stay finite, and follow MuJoCo on the same MJCF under the same open-loop actions.

The rollouts, actions and metrics live in ``tests/model_rollouts.py`` (``studies/check_models.py`` prints the full
table from them); here each model runs once at its recommended substep count, float64, eager, batch 3 (env 0: the
compared actions; env 1: zero controls; env 2: full-range random controls of another seed, for the divergence check).
"""

import mujoco
import pytest

import model_rollouts as cm
import torchsim

# (nq, nv, nu, bodies after fusing, contact pairs) of each model (brax.md section 2.2 for the layouts).
LAYOUT = {
    "hopper": (6, 6, 3, 4, 4),
    "walker2d": (9, 9, 6, 7, 7),
    "halfcheetah": (9, 9, 6, 7, 8),
    "reacher": (4, 4, 2, 3, 0),
    "inverted_pendulum": (2, 2, 1, 2, 0),
    "inverted_double_pendulum": (3, 3, 1, 3, 0),
    "pusher": (11, 11, 7, 8, 3),
}

# Bound on the compared trajectory error vs MuJoCo at the model's own timestep (tests/model_rollouts.py metric:
# root position [m] over 0.25 s for hopper/walker2d/halfcheetah, max |q| [rad, m] over 1 s for reacher and the
# pendulums, arm joints [rad] over 1 s for the pusher). Each is ~2-3x the measured error (spring, recommended
# substeps, MuJoCo 4.0); "MuJoCo dt vs dt/4" is MuJoCo's own timestep sensitivity on the same metric.
TOLERANCE = {
    "hopper": 0.06,                     # measured 0.027 m at 4 substeps; MuJoCo dt vs dt/4: 0.0010 m
    "walker2d": 0.2,                    # measured 0.094 m at 4 substeps (landing differs); MuJoCo: 0.0045 m
    "halfcheetah": 0.03,                # measured 0.011 m at 10 substeps; MuJoCo: 0.0083 m
    "reacher": 0.03,                    # measured 0.012 rad at 20 substeps, 0.1x controls; MuJoCo: 0.0097 rad
    "inverted_pendulum": 0.012,         # measured 0.0047 at 10 substeps, 0.1x controls; MuJoCo: 0.0049
    "inverted_double_pendulum": 0.1,    # measured 0.045 rad at 5 substeps, 0.02x controls; MuJoCo: 0.032 rad
    "pusher": 0.25,                     # measured 0.083 rad (arm joints) at 20 substeps; MuJoCo: 0.0055 rad
    "ant": 0.2,                         # measured 0.092 m at 20 substeps, full-range controls; MuJoCo: 0.038 m
    "humanoid": 0.05,                   # measured 0.019 m at 6 substeps; MuJoCo: 0.0060 m
}
NEW_MODELS = list(LAYOUT)


@pytest.mark.parametrize("name", NEW_MODELS)
def test_loads_with_layout_and_pairs(name):
    m = mujoco.MjModel.from_xml_path(cm.path(name))
    nq, nv, nu, bodies, pairs = LAYOUT[name]
    assert (m.nq, m.nv, m.nu) == (nq, nv, nu)
    for method in ("spring", "xpbd"):
        sys_ = torchsim.load_mjcf(cm.path(name), method=method)
        assert (sys_.nq, sys_.nv, sys_.nu, sys_.num_bodies) == (nq, nv, nu, bodies)
        assert sys_.num_contact_pairs == pairs


def test_humanoid_collides_through_feet_and_shins():
    sys_ = torchsim.load_mjcf(cm.path("humanoid"))
    assert (sys_.nq, sys_.nv, sys_.nu) == (24, 23, 17)
    assert sys_.num_contact_pairs == 4
    assert sorted(g.kind for g in sys_.contact_groups) == ["capsule_plane", "sphere_plane"]


@pytest.mark.parametrize("name", NEW_MODELS + ["humanoid"])
def test_poses_match_mujoco(name):
    err = cm.fk_error(name)
    print(f"{name}: pose error {err:.1e}")
    assert err < 1e-6


@pytest.mark.parametrize("name", list(TOLERANCE))
def test_follows_mujoco_and_stays_finite(name):
    m = mujoco.MjModel.from_xml_path(cm.path(name))
    acts = cm.actions(name, m)
    ref = cm.mujoco_rollout(name, acts=acts)
    ours = cm.torchsim_rollout(name, cm.MODELS[name]["substeps"], acts=acts, companions=True)
    err = cm.trajectory_error(name, ours, ref)
    print(f"{name}: error vs MuJoCo {err:.2e} (bound {TOLERANCE[name]}), travel {cm.travel(name, ours):.4f} "
          f"vs MuJoCo {cm.travel(name, ref):.4f}")
    assert not ours[2], "an env diverged or went non-finite"
    assert err < TOLERANCE[name]
    if name == "pusher":  # the wrist really pushes the object, as in MuJoCo
        assert cm.travel(name, ours) > 0.5 * cm.travel(name, ref) > 0.05
