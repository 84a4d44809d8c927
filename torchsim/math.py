"""Batched quaternion, rotation and small-matrix helpers.

Quaternions are ``(..., 4)`` tensors in MuJoCo's ``(w, x, y, z)`` order. Every function broadcasts over
leading dimensions and is free of data-dependent Python control flow, so it traces into one graph.
"""

import torch


def _quat_product_table() -> torch.Tensor:
    """(16, 4) table T with ``a ⊗ b = vec(a bᵀ) @ T``: the Hamilton product as one small matmul."""
    table = torch.zeros(4, 4, 4, dtype=torch.float64)
    rules = {  # (i, j) -> (k, sign): e_i e_j = sign e_k for the basis (1, i, j, k)
        (0, 0): (0, 1), (0, 1): (1, 1), (0, 2): (2, 1), (0, 3): (3, 1),
        (1, 0): (1, 1), (1, 1): (0, -1), (1, 2): (3, 1), (1, 3): (2, -1),
        (2, 0): (2, 1), (2, 1): (3, -1), (2, 2): (0, -1), (2, 3): (1, 1),
        (3, 0): (3, 1), (3, 1): (2, 1), (3, 2): (1, -1), (3, 3): (0, -1),
    }
    for (i, j), (k, sign) in rules.items():
        table[i, j, k] = sign
    return table.reshape(16, 4)


def _rotation_table() -> torch.Tensor:
    """(16, 9) table T with ``R(q) = vec(q qᵀ) @ T`` for unit ``q``: rotation entries are quadratic in q."""
    table = torch.zeros(4, 4, 3, 3, dtype=torch.float64)
    w, x, y, z = range(4)
    entries = {
        (0, 0): [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)], (1, 1): [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)],
        (2, 2): [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
        (0, 1): [(x, y, 2), (w, z, -2)], (0, 2): [(x, z, 2), (w, y, 2)], (1, 0): [(x, y, 2), (w, z, 2)],
        (1, 2): [(y, z, 2), (w, x, -2)], (2, 0): [(x, z, 2), (w, y, -2)], (2, 1): [(y, z, 2), (w, x, 2)],
    }
    for (r, c), terms in entries.items():
        for i, j, coef in terms:
            table[i, j, r, c] += coef
    return table.reshape(16, 9)


def _skew_table() -> torch.Tensor:
    table = torch.zeros(3, 3, 3, dtype=torch.float64)
    table[2, 1, 0], table[1, 2, 0] = 1, -1
    table[2, 0, 1], table[0, 2, 1] = -1, 1
    table[1, 0, 2], table[0, 1, 2] = 1, -1
    return table.permute(2, 0, 1).reshape(3, 9)


_TABLES = {"quat_product": _quat_product_table(), "rotation": _rotation_table(), "skew": _skew_table(),
           "conj": torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=torch.float64),
           "eye3": torch.eye(3, dtype=torch.float64)}
_CACHE: dict = {}


def _table(name: str, like: torch.Tensor) -> torch.Tensor:
    """A constant table in ``like``'s dtype and device, converted once."""
    key = (name, like.dtype, like.device)
    if key not in _CACHE:
        _CACHE[key] = _TABLES[name].to(dtype=like.dtype, device=like.device)
    return _CACHE[key]


def eye3(like: torch.Tensor) -> torch.Tensor:
    """The 3x3 identity in ``like``'s dtype and device (a cached constant, not rebuilt every call)."""
    return _table("eye3", like)


def mm(*mats: torch.Tensor) -> torch.Tensor:
    """Product of small matrices, left to right, broadcasting over leading dimensions.

    Eager mode uses ``@`` (one library kernel per product). Under ``torch.compile`` each product is a broadcast
    multiply-and-sum instead, which inductor fuses into the surrounding kernels: a ``@`` would stay an opaque
    library call per product there, and batched 3x3 (or vector-by-table) products are slow ones.
    """
    out = mats[0]
    for m in mats[1:]:
        out = (out.unsqueeze(-1) * m.unsqueeze(-3)).sum(-2) if torch.compiler.is_compiling() else out @ m
    return out


def _table_product(x: torch.Tensor, name: str) -> torch.Tensor:
    """``x @ T`` for a constant table ``T (K, M)`` and row vectors ``x (..., K)``, fusable when compiled (see ``mm``)."""
    table = _table(name, x)
    return (x.unsqueeze(-1) * table).sum(-2) if torch.compiler.is_compiling() else x @ table


def cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product over the last axis, broadcasting."""
    if a.ndim < b.ndim:
        a = a.view((1,) * (b.ndim - a.ndim) + a.shape)
    elif b.ndim < a.ndim:
        b = b.view((1,) * (a.ndim - b.ndim) + b.shape)
    if not torch.compiler.is_compiling():
        return torch.linalg.cross(a, b, dim=-1)
    (ax, ay, az), (bx, by, bz) = a.unbind(-1), b.unbind(-1)
    return torch.stack((ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx), -1)


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Inner product over the last axis, keeping it as a size-1 axis."""
    return (a * b).sum(-1, keepdim=True)


def safe_norm(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Euclidean norm over the last axis (kept), with a finite gradient at zero."""
    return torch.sqrt((v * v).sum(-1, keepdim=True) + eps)


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / safe_norm(v, eps)


def _outer_flat(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b``."""
    if not torch.compiler.is_compiling():
        return _table_product(_outer_flat(a, b), "quat_product")
    (aw, ax, ay, az), (bw, bx, by, bz) = a.unbind(-1), b.unbind(-1)
    return torch.stack((aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw), -1)


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    return q * _table("conj", q)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vector ``v`` by unit quaternion ``q`` (``q v q*``), without building a matrix."""
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + q[..., :1] * t + cross(u, t)


def quat_rotate_inv(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate ``v`` by the inverse of unit quaternion ``q``."""
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v - q[..., :1] * t + cross(u, t)


def quat_to_mat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``(..., 3, 3)`` of unit quaternion ``q``."""
    if not torch.compiler.is_compiling():
        return _table_product(_outer_flat(q, q), "rotation").unflatten(-1, (3, 3))
    w, x, y, z = q.unbind(-1)
    return torch.stack((w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z), -1).unflatten(-1, (3, 3))


def axis_angle_to_quat(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Quaternion of a rotation by ``angle`` (``(...)``) about unit ``axis`` (``(..., 3)``)."""
    half = 0.5 * angle.unsqueeze(-1)
    return torch.cat((torch.cos(half), axis * torch.sin(half)), dim=-1)


def quat_integrate(q: torch.Tensor, ang_vel: torch.Tensor, dt: float) -> torch.Tensor:
    """Advance orientation ``q`` by world-frame angular velocity ``ang_vel`` over ``dt`` (exact exponential map)."""
    angle = safe_norm(ang_vel, 1e-30) * dt
    dq = torch.cat((torch.cos(0.5 * angle), ang_vel * (dt * torch.sin(0.5 * angle) / angle)), dim=-1)
    return normalize(quat_mul(dq, q))


def quat_to_rot_vec(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector (axis times angle in [0, pi]) of unit quaternion ``q``; the inverse of the exponential map."""
    w = q[..., :1]
    sign = torch.where(w < 0, -1.0, 1.0)
    sin_half = safe_norm(q[..., 1:], 1e-30)
    return q[..., 1:] * (2.0 * sign * torch.atan2(sin_half, sign * w) / sin_half)


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[v]x`` with ``[v]x u = v × u``."""
    if not torch.compiler.is_compiling():
        return _table_product(v, "skew").unflatten(-1, (3, 3))
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1).unflatten(-1, (3, 3))


def inv3(m: torch.Tensor) -> torch.Tensor:
    """Inverse of ``(..., 3, 3)`` matrices from cross products of their columns (no LAPACK call)."""
    cols = m.transpose(-1, -2)
    c0, c1, c2 = cols[..., 0, :], cols[..., 1, :], cols[..., 2, :]
    rows = torch.stack((cross(c1, c2), cross(c2, c0), cross(c0, c1)), -2)
    return rows / (rows[..., 0, :] * c0).sum(-1)[..., None, None]


def spd_solve(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solution ``x (..., n)`` of ``a x = b`` for symmetric positive-definite ``a (..., n, n)``.

    Eager mode calls LAPACK through ``solve_ex``, which skips the per-call singularity check, so one diverged
    env's matrix cannot raise for the whole batch. Under ``torch.compile`` the Cholesky factorisation and both
    substitutions are unrolled over ``n`` into elementwise ops that inductor fuses with the rest of the substep:
    a LAPACK call would split the substep's kernel in two and, in inductor's C++ wrapper, go through a slow
    fallback (there is no C shim for it).
    """
    if not torch.compiler.is_compiling():
        return torch.linalg.solve_ex(a, b).result
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]  # low[i][j], j <= i: the Cholesky factor L, a = L L^T
    inv_diag = [None] * n
    for j in range(n):
        inv_diag[j] = torch.rsqrt(a[..., j, j] - sum(low[j][k] * low[j][k] for k in range(j)))
        low[j][j] = 1.0 / inv_diag[j]
        for i in range(j + 1, n):
            low[i][j] = (a[..., i, j] - sum(low[i][k] * low[j][k] for k in range(j))) * inv_diag[j]
    y = [None] * n  # L y = b
    for i in range(n):
        y[i] = (b[..., i] - sum(low[i][k] * y[k] for k in range(i))) * inv_diag[i]
    x = [None] * n  # L^T x = y
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) * inv_diag[i]
    return torch.stack(x, -1)


def matvec(m: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``m @ v`` for ``(..., 3, 3)`` by ``(..., 3)``."""
    return (m * v.unsqueeze(-2)).sum(-1)


def angle_about(axis: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Signed angle ``(...)`` that rotates ``u`` onto ``v`` about unit ``axis``, measured in the plane normal to it."""
    u_p = u - dot(u, axis) * axis
    v_p = v - dot(v, axis) * axis
    return torch.atan2((axis * cross(u_p, v_p)).sum(-1), (u_p * v_p).sum(-1))
