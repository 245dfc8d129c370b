"""Batched rigid-body poses: position + unit quaternion, exponential and logarithm maps.

A pose is a tensor of shape ``(..., 7)`` laid out as ``[px, py, pz, qw, qx, qy, qz]``: the position in
metres and the unit quaternion (Hamilton convention, scalar first) of the rotation from the body frame
to the parent frame. A pose maps body-frame points to parent-frame points: ``x = R(q) x_b + p``.
Twists ``xi`` are ``(..., 6)`` = ``[v (m), omega (rad)]``, with ``omega`` a rotation vector.

Every function is batched over the leading dimensions, keeps the dtype and device of its inputs and is
differentiable. The exponential and logarithm maps switch to Taylor series below a small-angle
threshold chosen per dtype, with the "double where" pattern so that the branch not taken never feeds a
NaN or an infinity into the gradient: values and gradients are finite and exact at and near zero
rotation (and near a half turn for the logarithms).
"""
from __future__ import annotations

import functools

import torch
from torch import Tensor


def safe_norm(v: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """Euclidean norm along ``dim`` whose gradient is finite (zero) at the zero vector.

    ``sqrt(max(sum(v^2), tiny))`` with ``tiny`` the smallest normal number of ``v``'s dtype, so the
    value differs from the exact norm by at most ``sqrt(tiny)`` (1e-154 in float64, 1e-19 in float32).
    """
    sq = (v * v).sum(dim=dim, keepdim=keepdim)
    return sq.clamp_min(torch.finfo(v.dtype).tiny).sqrt()


def _small_angle_sq(dtype: torch.dtype) -> float:
    """Squared angle (rad^2) below which the series are used: eps^(1/4), 1.2e-4 in float64, 1.9e-2 in float32.

    The series are kept to the theta^4 term, so their truncation error (~theta^6 / 6e4) is below eps,
    while the closed forms used above the threshold lose at most eps / theta^2 to cancellation.
    """
    return torch.finfo(dtype).eps ** 0.25


def _split(x2: Tensor) -> tuple[Tensor, Tensor]:
    """Mask ``x2 < threshold`` and the magnitude ``sqrt(x2)`` made safe (1.0) where the mask holds."""
    small = x2 < _small_angle_sq(x2.dtype)
    return small, torch.where(small, torch.ones_like(x2), x2).sqrt()


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product over the last axis (size 3), broadcasting the leading dimensions.

    Under ``torch.compile`` it is spelled out per component, which inductor fuses into the kernels around it
    (aten's cross is an external call it cannot fuse); eager, it is aten's one call.
    """
    if torch.compiler.is_compiling():
        ax, ay, az = a.unbind(-1)
        bx, by, bz = b.unbind(-1)
        return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], dim=-1)
    a, b = torch.broadcast_tensors(a, b)
    return torch.linalg.cross(a, b, dim=-1)


def small_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for ``a (..., m, k)``, ``b (..., k, n)`` with a short contraction (a rotation applied to points,
    a product of 3 x 3 matrices) or small operands (a 3 x 3 moment summed over points).

    Under ``torch.compile`` it is a sum of broadcast products, which inductor fuses into the kernels around it: a
    batched matmul is an external BLAS call per batch of tiny matrices, which it cannot fuse and which costs more
    than the arithmetic. Eager, it is the matmul (one call, where the broadcast form would allocate
    ``(..., m, k, n)``).
    """
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return a @ b


def small_spd_solve(a: Tensor, b: Tensor) -> Tensor:
    """``x (..., d)`` with ``a x = b`` for small symmetric positive definite ``a (..., d, d)`` (d <= 6: a mass
    matrix plus a contact stiffness) and ``b (..., d)``.

    Under ``torch.compile`` it is a Cholesky factorisation and two triangular solves written out entry by entry,
    elementwise over the batch, which inductor fuses into one kernel: its ``linalg.solve`` is an external LAPACK
    call per batch that it cannot fuse (and with the C++ wrapper, a call through its slow proxy executor). Eager,
    it is ``torch.linalg.solve``. A non-finite ``a`` gives a non-finite ``x``.
    """
    if not torch.compiler.is_compiling():
        return torch.linalg.solve(a, b.unsqueeze(-1)).squeeze(-1)
    d = a.shape[-1]
    zero = torch.zeros_like(b[..., 0])
    factor: list[list[Tensor]] = [[] for _ in range(d)]  # rows of the lower Cholesky factor L
    for j in range(d):
        for i in range(j, d):
            rest = a[..., i, j] - sum((factor[i][k] * factor[j][k] for k in range(j)), zero)
            factor[i].append(torch.sqrt(rest) if i == j else rest / factor[j][j])
    y: list[Tensor] = []
    for i in range(d):
        y.append((b[..., i] - sum((factor[i][k] * y[k] for k in range(i)), zero)) / factor[i][i])
    x: list[Tensor] = [zero] * d
    for i in reversed(range(d)):
        x[i] = (y[i] - sum((factor[k][i] * x[k] for k in range(i + 1, d)), zero)) / factor[i][i]
    return torch.stack(x, dim=-1)


# ----------------------------------------------------------------------------------------------------
# Quaternions (..., 4) = [w, x, y, z]
# ----------------------------------------------------------------------------------------------------


def quat_normalize(q: Tensor) -> Tensor:
    """Unit quaternion ``q / |q|``; ``q`` is ``(..., 4)``."""
    return q / safe_norm(q, keepdim=True)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a ⊗ b`` (apply ``b`` first, then ``a``); ``(..., 4)`` each, broadcast."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate ``[w, -x, -y, -z]`` (the inverse of a unit quaternion); ``(..., 4)``."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``; leading dims broadcast."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


#: Entry ``i`` of a rotation matrix (row-major) is ``BASE[i] + OUTER[i] * s * (qq[A[i]] + INNER[i] * qq[B[i]])``, with
#: ``qq`` the flattened outer product ``q q^T`` (order w, x, y, z) and ``s = 2 / |q|^2``: the two products of each
#: entry, the sign between them, the sign of the sum and the identity.
_ROTATION_PRODUCTS_A = (10, 6, 7, 6, 5, 11, 7, 11, 5)
_ROTATION_PRODUCTS_B = (15, 3, 2, 3, 15, 1, 2, 1, 10)
_ROTATION_INNER_SIGNS = (1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0)
_ROTATION_OUTER_SIGNS = (-1.0, 1.0, 1.0, 1.0, -1.0, 1.0, 1.0, 1.0, -1.0)
_ROTATION_BASE = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@functools.lru_cache(maxsize=None)
def _rotation_tables(device: torch.device, dtype: torch.dtype) -> tuple[Tensor, ...]:
    """The index and sign tables of ``quat_to_matrix``'s eager form, made once per device and dtype. Made outside
    inference mode, so that they are ordinary tensors whatever mode the first call ran in (a product with them that
    needs gradients saves them)."""
    with torch.inference_mode(False):
        return (
            torch.tensor(_ROTATION_PRODUCTS_A, device=device),
            torch.tensor(_ROTATION_PRODUCTS_B, device=device),
            *(torch.tensor(t, dtype=dtype, device=device)
              for t in (_ROTATION_INNER_SIGNS, _ROTATION_OUTER_SIGNS, _ROTATION_BASE)),
        )


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrix ``(..., 3, 3)`` of quaternions ``q (..., 4)`` (normalized on the fly).

    Two forms with the same values bit for bit: in eager, one outer product and two gathers (12 tensor operations,
    0.4 of the time of the 47 of the entry-by-entry form); in a compiled graph, the entry-by-entry form, which
    inductor fuses into one pointwise kernel (the gathers would be indirect loads, 6 times as slow).
    """
    if torch.compiler.is_compiling():
        w, x, y, z = q.unbind(-1)
        s = 2.0 / (q * q).sum(-1)
        rows = (
            (1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)),
            (s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)),
            (s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)),
        )
        return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)
    first, second, inner, outer, base = _rotation_tables(q.device, q.dtype)
    s = 2.0 / (q * q).sum(-1)
    qq = (q.unsqueeze(-1) * q.unsqueeze(-2)).flatten(-2)
    pairs = qq.index_select(-1, first) + inner * qq.index_select(-1, second)
    return (base + outer * (s.unsqueeze(-1) * pairs)).unflatten(-1, (3, 3))


def matrix_to_quat(R: Tensor) -> Tensor:
    """Unit quaternion ``(..., 4)`` with ``w >= 0`` of rotation matrices ``R (..., 3, 3)``.

    Shepperd's method: of the four algebraically equivalent formulas, the one dividing by the largest
    of ``4w^2, 4x^2, 4y^2, 4z^2`` (always >= 1) is used, so it is accurate for every rotation.
    """
    r = R.unbind(-1)
    r00, r10, r20 = r[0].unbind(-1)
    r01, r11, r21 = r[1].unbind(-1)
    r02, r12, r22 = r[2].unbind(-1)
    t = torch.stack(
        (1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22), dim=-1
    )
    candidates = torch.stack(
        (
            torch.stack((t[..., 0], r21 - r12, r02 - r20, r10 - r01), dim=-1),
            torch.stack((r21 - r12, t[..., 1], r01 + r10, r02 + r20), dim=-1),
            torch.stack((r02 - r20, r01 + r10, t[..., 2], r12 + r21), dim=-1),
            torch.stack((r10 - r01, r02 + r20, r12 + r21, t[..., 3]), dim=-1),
        ),
        dim=-2,
    ) / (2.0 * t.clamp_min(0.1).sqrt()).unsqueeze(-1)
    best = t.argmax(dim=-1, keepdim=True)
    q = candidates.gather(-2, best.unsqueeze(-1).expand(*best.shape, 4)).squeeze(-2)
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


# ----------------------------------------------------------------------------------------------------
# Poses (..., 7) = [p, q]
# ----------------------------------------------------------------------------------------------------


def identity(batch_shape=(), dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """Identity poses of shape ``(*batch_shape, 7)``."""
    pose = torch.zeros(*batch_shape, 7, dtype=dtype, device=device)
    pose[..., 3] = 1.0
    return pose


def compose(a: Tensor, b: Tensor) -> Tensor:
    """Pose ``T_a · T_b`` (apply ``b`` first, then ``a``); ``(..., 7)`` each, broadcast."""
    pa, qa = a[..., :3], a[..., 3:]
    pb, qb = b[..., :3], b[..., 3:]
    return torch.cat((pa + quat_rotate(qa, pb), quat_multiply(qa, qb)), dim=-1)


def inverse(a: Tensor) -> Tensor:
    """Inverse pose ``T_a^{-1}``; ``(..., 7)``."""
    qi = quat_conjugate(a[..., 3:])
    return torch.cat((-quat_rotate(qi, a[..., :3]), qi), dim=-1)


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Map points ``(..., N, 3)`` (m) by poses ``(..., 7)`` broadcast over the point axis: ``R x + p``."""
    pose = pose.unsqueeze(-2)
    return quat_rotate(pose[..., 3:], points) + pose[..., :3]


def rotate_vectors(pose: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``(..., N, 3)`` by the rotation of poses ``(..., 7)`` (no translation)."""
    return quat_rotate(pose[..., 3:].unsqueeze(-2), v)


# ----------------------------------------------------------------------------------------------------
# Exponential and logarithm maps
# ----------------------------------------------------------------------------------------------------


def so3_exp(omega: Tensor) -> Tensor:
    """Quaternion ``(..., 4)`` of rotation vectors ``omega (..., 3)`` (rad): angle |omega| about omega."""
    t2 = (omega * omega).sum(-1, keepdim=True)
    small, t = _split(t2)
    # cos(t/2) and sin(t/2)/t, with their Taylor series about t = 0.
    c = torch.where(small, 1 - t2 / 8 + t2 * t2 / 384, torch.cos(t / 2))
    s = torch.where(small, 0.5 - t2 / 48 + t2 * t2 / 3840, torch.sin(t / 2) / t)
    return torch.cat((c, s * omega), dim=-1)


def so3_log(q: Tensor) -> Tensor:
    """Rotation vector ``(..., 3)`` (rad, norm in [0, pi]) of quaternions ``q (..., 4)``.

    ``q`` and ``-q`` give the same result (the shortest rotation), and so does any positive rescaling
    of ``q``. Finite gradients at zero rotation and at a half turn.
    """
    q = torch.where(q[..., :1] < 0, -q, q)
    w, u = q[..., :1], q[..., 1:]
    s2 = (u * u).sum(-1, keepdim=True)
    small, s = _split(s2)
    # angle / sin(angle/2) = 2 atan2(s, w) / s; for small s, with x = s / w = tan(angle/2):
    # 2 atan(x) / s = (2 / w) (1 - x^2/3 + x^4/5).
    w_small = torch.where(small, w, torch.ones_like(w))
    x2 = s2 / (w_small * w_small)
    k = torch.where(small, 2 / w_small * (1 - x2 / 3 + x2 * x2 / 5), 2 * torch.atan2(s, w) / s)
    return k * u


def _skew_terms(omega: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Pieces shared by the SE(3) maps: ``t^2``, safe ``t``, small-angle mask, ``w×v``, ``w×(w×v)``.

    ``omega`` and ``v`` are ``(..., 3)``; ``t = |omega|`` is 1.0 where the mask holds, so closed forms
    divide by ``t * t`` (never by ``t^2``, which may be zero there).
    """
    t2 = (omega * omega).sum(-1, keepdim=True)
    small, t = _split(t2)
    wv = _cross(omega, v)
    return t2, t, small, wv, _cross(omega, wv)


def se3_exp(xi: Tensor) -> Tensor:
    """Pose ``(..., 7)`` of twists ``xi (..., 6) = [v (m), omega (rad)]``: ``p = V v``, ``q = exp(omega)``.

    ``V = I + B [w]x + C [w]x^2`` is the left Jacobian of SO(3), ``B = (1 - cos t)/t^2``,
    ``C = (t - sin t)/t^3``, ``t = |omega|``.
    """
    v, omega = xi[..., :3], xi[..., 3:]
    t2, t, small, wv, wwv = _skew_terms(omega, v)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, 2 * torch.sin(t / 2) ** 2 / (t * t))
    c = torch.where(small, 1 / 6 - t2 / 120 + t2 * t2 / 5040, (t - torch.sin(t)) / (t * t * t))
    return torch.cat((v + b * wv + c * wwv, so3_exp(omega)), dim=-1)


def se3_log(pose: Tensor) -> Tensor:
    """Twist ``(..., 6) = [v (m), omega (rad)]`` of poses ``(..., 7)``; inverse of :func:`se3_exp`.

    ``v = V^{-1} p`` with ``V^{-1} = I - [w]x / 2 + D [w]x^2``, ``D = (1 - (t/2) cot(t/2)) / t^2``.
    The rotation is the shortest one (angle <= pi).
    """
    p = pose[..., :3]
    omega = so3_log(pose[..., 3:])
    t2, t, small, wv, wwv = _skew_terms(omega, p)
    half = t / 2
    d = torch.where(
        small,
        1 / 12 + t2 / 720 + t2 * t2 / 30240,
        (1 - half * torch.cos(half) / torch.sin(half)) / (t * t),
    )
    return torch.cat((p - wv / 2 + d * wwv, omega), dim=-1)


def retract(pose: Tensor, delta: Tensor) -> Tensor:
    """Decoupled world-frame update of poses ``(..., 7)`` by ``delta (..., 6) = [dp (m), dtheta (rad)]``.

    ``p' = p + dp`` and ``q' = exp(dtheta) ⊗ q`` (a rotation about the pose's own origin, axis in the
    parent frame), re-normalized.
    """
    q = quat_normalize(quat_multiply(so3_exp(delta[..., 3:]), pose[..., 3:]))
    return torch.cat((pose[..., :3] + delta[..., :3], q), dim=-1)


# ----------------------------------------------------------------------------------------------------
# Planar poses and angles
# ----------------------------------------------------------------------------------------------------


def se2_to_se3(xy_yaw: Tensor, z: float = 0.0) -> Tensor:
    """Poses ``(..., 7)`` at height ``z`` (m) of planar poses ``(..., 3) = [x (m), y (m), yaw (rad)]``."""
    half = xy_yaw[..., 2:] / 2
    zeros = torch.zeros_like(half)
    return torch.cat(
        (xy_yaw[..., :2], torch.full_like(half, z), torch.cos(half), zeros, zeros, torch.sin(half)), dim=-1
    )


def yaw(pose: Tensor) -> Tensor:
    """Yaw (rad, in (-pi, pi]) of poses ``(..., 7)``: the z angle of the z-y-x Euler decomposition.

    The gradient is undefined only at gimbal lock (body x axis along world z).
    """
    w, x, y, z = pose[..., 3:].unbind(-1)
    return torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def se3_to_se2(pose: Tensor) -> Tensor:
    """Planar poses ``(..., 3) = [x, y, yaw]`` of poses ``(..., 7)`` (height and tilt dropped)."""
    return torch.cat((pose[..., :2], yaw(pose).unsqueeze(-1)), dim=-1)


def angle_between(qa: Tensor, qb: Tensor) -> Tensor:
    """Geodesic angle ``(...)`` (rad, in [0, pi]) between rotations ``qa, qb (..., 4)``.

    ``2 atan2(|vec(d)|, |w(d)|)`` with ``d = conj(qa) ⊗ qb``, so ``q`` and ``-q`` are the same rotation;
    the gradient is finite everywhere (zero where ``qa = ±qb``).
    """
    d = quat_multiply(quat_conjugate(qa), qb)
    return 2 * torch.atan2(safe_norm(d[..., 1:]), d[..., 0].abs())
