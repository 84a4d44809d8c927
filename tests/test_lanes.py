"""The lanes layout (``torchsim.lanes``): exact conversions to and from the public batch-first layout, System fields
as broadcastable views, and the math helpers agreeing with independent formulas in both layouts."""

import torch

from models import quat_to_mat
from torchsim import lanes, spatial

F64 = torch.float64


def test_conversions_round_trip_and_place_components_first():
    x = torch.randn(5, 7, 3, 3, dtype=F64)  # (B, E, C, C)
    y = lanes.to_lanes(x, 2)
    assert y.shape == (3, 3, 7, 5) and torch.equal(y[1, 2, 4, 3], x[3, 4, 1, 2])
    assert torch.equal(lanes.from_lanes(y, 2), x)
    scalars = torch.randn(5, 7, 6, dtype=F64)  # two entity axes, no components
    assert torch.equal(lanes.from_lanes(lanes.to_lanes(scalars)), scalars)


def test_param_gives_a_batch_axis_of_one_or_b():
    inertia = torch.randn(7, 3, 3, dtype=F64)
    assert lanes.param(inertia, 1, 2).shape == (3, 3, 7, 1)
    assert torch.equal(lanes.param(inertia, 1, 2)[..., 0], inertia.permute(1, 2, 0))
    per_env = torch.randn(5, 7, 3, 3, dtype=F64)
    assert torch.equal(lanes.param(per_env, 1, 2), lanes.to_lanes(per_env, 2))
    assert lanes.param(torch.randn(7, 2, dtype=F64), 2).shape == (7, 2, 1)
    assert lanes.param(torch.randn(5, 7, dtype=F64), 1).shape == (7, 5)


def test_math_matches_independent_formulas():
    """Lanes inputs (vectors (3, N, B)) and batch-first ones through ``components_last`` give the rotation that
    an independently written quaternion-to-matrix formula gives."""
    q = torch.nn.functional.normalize(torch.randn(5, 7, 4, dtype=F64), dim=-1)
    v = torch.randn(5, 7, 3, dtype=F64)
    expected = (quat_to_mat(q) @ v[..., None])[..., 0]
    rotated = spatial.quat_rotate(lanes.to_lanes(q, 1), lanes.to_lanes(v, 1))
    torch.testing.assert_close(lanes.from_lanes(rotated, 1), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(lanes.components_last(spatial.quat_rotate)(q, v), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(lanes.components_last(spatial.quat_to_mat, 2)(q), quat_to_mat(q), rtol=0, atol=1e-12)
    # a constant vector broadcasts against batch-first tensors as it would in batch-first arithmetic
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    torch.testing.assert_close(lanes.components_last(spatial.quat_rotate)(q, axis), quat_to_mat(q)[..., 2],
                               rtol=0, atol=1e-12)
    m = torch.randn(5, 7, 3, 3, dtype=F64) + 3 * torch.eye(3, dtype=F64)
    inverse = lanes.from_lanes(spatial.inv3(lanes.to_lanes(m, 2)), 2)
    torch.testing.assert_close(inverse @ m, torch.eye(3, dtype=F64).expand_as(m), rtol=0, atol=1e-10)
    # spd_solve broadcasts a right-hand side with more batch axes than the matrix: 4 columns of the identity
    # against a (4, 4, B) matrix give its inverse
    root = torch.randn(5, 4, 4, dtype=F64)
    spd = root @ root.transpose(-1, -2) + 4 * torch.eye(4, dtype=F64)
    solved = spatial.spd_solve(lanes.to_lanes(spd, 2), torch.eye(4, dtype=F64)[..., None])  # (4, 4, B)
    torch.testing.assert_close(lanes.from_lanes(solved, 2) @ spd, torch.eye(4, dtype=F64).expand_as(spd),
                               rtol=0, atol=1e-10)
