"""The load-time incidence tables behind the coupled solves (``joint_space.incidence_tables``): which items (hinge
dofs, contact points) act on which body, and every ordered pair of them on a common body, built in time linear in
their size; the soft contacts' tables of a model whose bodies touch each other; impulse contacts skip them."""

import numpy as np
import torch

import torchsim
from torchsim import joint_space
from torchsim.system import POINTS_PER_PAIR
from models import F64

# Two free boxes and a free sphere over a plane: plane-box (8 points each), plane-sphere (1), box-box (16) and
# box-sphere (1 each), so the moving bodies meet contact points as the pair's first and as its second body.
BODIES_THAT_TOUCH = """
<mujoco><worldbody>
  <geom type="plane" size="5 5 .1"/>
  <body pos="0 0 .2"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
  <body pos=".15 0 .2"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
  <body pos="0 .15 .2"><freejoint/><geom type="sphere" size=".1"/></body>
</worldbody></mujoco>"""


def expected_pairs(body: list) -> list:
    """The tables' meaning: every ordered pair ``(i, k)`` of rows on a common body, ``i`` ascending, then ``k``."""
    return [(i, k) for i in range(len(body)) for k in range(len(body)) if body[i] == body[k]]


def test_pairs_are_every_ordered_pair_on_a_common_body():
    """Random incidences, grouped by body as the loaders give them and shuffled: the columns come back as given and
    the pairs are exactly the ordered pairs of rows on one body, in order."""
    rng = np.random.default_rng(0)
    grouped = sorted((int(b), int(i), float(s)) for b, i, s in
                     zip(rng.integers(0, 7, 60), rng.integers(0, 40, 60), rng.choice([-1.0, 1.0], 60)))
    shuffled = [grouped[i] for i in rng.permutation(len(grouped))]
    for rows in (grouped, shuffled):
        body, item, sign, pairs = joint_space.incidence_tables(rows)
        assert body.tolist() == [r[0] for r in rows] and item.tolist() == [r[1] for r in rows]
        assert sign.tolist() == [r[2] for r in rows] and sign.dtype == torch.float64 and body.dtype == torch.long
        assert [tuple(p) for p in pairs.tolist()] == expected_pairs([r[0] for r in rows])
    body, item, sign, pairs = joint_space.incidence_tables([])
    assert body.shape == item.shape == sign.shape == (0,) and pairs.shape == (0, 2)


def test_soft_contact_tables_list_each_points_bodies():
    """Each contact point acts on its pair's moving bodies, +1 on the first (the normal pushes it) and -1 on the
    second, and the tables list exactly those incidences, grouped by body, then by point; impulse contacts, which
    never read them, get empty tables."""
    sys = torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64, contact_model="soft")
    world = sys.num_bodies
    expected = set()
    point = 0
    for group in sys.contact_groups:
        for a, b in zip(group.geom_a.tolist(), group.geom_b.tolist()):
            for _ in range(POINTS_PER_PAIR[group.kind]):
                for geom, sign in ((a, 1.0), (b, -1.0)):
                    if sys.geom_body[geom] != world:
                        expected.add((point, int(sys.geom_body[geom]), sign))
                point += 1
    body = sys.contact_inc_body.tolist()
    rows = list(zip(sys.contact_inc_point.tolist(), body, sys.contact_inc_sign.tolist()))
    assert point == sys.num_contacts and len(rows) == len(set(rows)) and set(rows) == expected
    assert body == sorted(body) and any(s < 0 for _, _, s in rows)
    assert rows == sorted(expected, key=lambda row: (row[1], row[0], row[2]))  # by body, then point
    assert [tuple(p) for p in sys.contact_inc_pairs.tolist()] == expected_pairs(body)
    impulse = torchsim.load_mjcf(BODIES_THAT_TOUCH, dtype=F64)
    assert impulse.num_contacts == sys.num_contacts
    assert impulse.contact_inc_point.numel() == 0 and impulse.contact_inc_pairs.shape == (0, 2)
