"""Tests of hydrosoft.geometry.se3: round trips, independent references, gradients at singular points."""
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hydrosoft.geometry import se3

F64 = torch.float64
coord = st.floats(-2.0, 2.0, allow_nan=False)
vec3 = st.lists(coord, min_size=3, max_size=3)


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew matrix (..., 3, 3) of w (..., 3)."""
    z = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack(
        (torch.stack((z, -wz, wy), -1), torch.stack((wz, z, -wx), -1), torch.stack((-wy, wx, z), -1)), -2
    )


def random_poses(n: int, seed: int = 0, dtype=F64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(n, 3, generator=g, dtype=dtype)
    q = se3.quat_normalize(torch.randn(n, 4, generator=g, dtype=dtype))
    return torch.cat((p, q), -1)


def pose_from_list(values) -> torch.Tensor:
    p = torch.tensor(values[:3], dtype=F64)
    q = torch.tensor(values[3:], dtype=F64)
    q = torch.where(q.norm() < 1e-3, torch.tensor([1.0, 0, 0, 0], dtype=F64), q)
    return torch.cat((p, se3.quat_normalize(q)))


pose_strategy = st.lists(coord, min_size=7, max_size=7).map(pose_from_list)


def test_identity():
    pose = se3.identity((2, 3), dtype=torch.float32)
    assert pose.shape == (2, 3, 7) and pose.dtype == torch.float32
    assert torch.equal(pose[0, 0], torch.tensor([0, 0, 0, 1, 0, 0, 0], dtype=torch.float32))
    x = torch.randn(2, 3, 5, 3)
    assert torch.allclose(se3.transform_points(se3.identity((2, 3), dtype=torch.float32), x), x)


def test_quat_multiply_matches_matrix_product():
    a, b = random_poses(50, 1)[:, 3:], random_poses(50, 2)[:, 3:]
    lhs = se3.quat_to_matrix(se3.quat_multiply(a, b))
    assert torch.allclose(lhs, se3.quat_to_matrix(a) @ se3.quat_to_matrix(b), atol=1e-12)
    identity = se3.quat_to_matrix(se3.quat_multiply(a, se3.quat_conjugate(a)))
    assert torch.allclose(identity, torch.eye(3, dtype=F64).expand(50, 3, 3), atol=1e-12)


def test_quat_rotate_matches_matrix_and_broadcasts():
    q = random_poses(4, 3)[:, 3:]
    v = torch.randn(5, 3, dtype=F64)
    out = se3.quat_rotate(q[:, None, :], v[None])
    assert out.shape == (4, 5, 3)
    ref = torch.einsum("bij,nj->bni", se3.quat_to_matrix(q), v)
    assert torch.allclose(out, ref, atol=1e-12)
    assert torch.allclose(out.norm(dim=-1), v.norm(dim=-1).expand(4, 5), atol=1e-12)


def test_quat_to_matrix_is_rotation():
    R = se3.quat_to_matrix(random_poses(100, 4)[:, 3:])
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(100, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(100, dtype=F64), atol=1e-12)


def test_matrix_to_quat_round_trip_including_half_turns():
    q = random_poses(200, 5)[:, 3:]
    half_turns = torch.tensor(
        [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0], [1, 0, 0, 0], [0.0, 0.0, 0.6, -0.8]],
        dtype=F64,
    )
    q = torch.cat((q, half_turns))
    back = se3.matrix_to_quat(se3.quat_to_matrix(q))
    assert (back[:, 0] >= 0).all()
    assert torch.allclose(back.norm(dim=-1), torch.ones(len(q), dtype=F64), atol=1e-12)
    # same rotation: equal up to sign
    assert torch.allclose(back.abs(), q.abs(), atol=1e-12)
    assert torch.allclose(se3.quat_to_matrix(back), se3.quat_to_matrix(q), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(pose_strategy, pose_strategy)
def test_compose_inverse_and_points(a, b):
    x = torch.randn(6, 3, dtype=F64)
    ab = se3.compose(a, b)
    nested = se3.transform_points(a, se3.transform_points(b, x))
    assert torch.allclose(se3.transform_points(ab, x), nested, atol=1e-12)
    for pose in (se3.compose(a, se3.inverse(a)), se3.compose(se3.inverse(a), a)):
        assert torch.allclose(se3.transform_points(pose, x), x, atol=1e-12)
    assert torch.allclose(ab[3:].norm(), torch.ones((), dtype=F64), atol=1e-12)
    assert torch.allclose(se3.rotate_vectors(a, x), se3.transform_points(a, x) - a[:3], atol=1e-12)


def test_transform_points_broadcasts_over_batch():
    poses = random_poses(6, 6).reshape(2, 3, 7)
    pts = torch.randn(2, 3, 10, 3, dtype=F64)
    out = se3.transform_points(poses, pts)
    assert out.shape == (2, 3, 10, 3)
    R = se3.quat_to_matrix(poses[..., 3:])
    ref = torch.einsum("bmij,bmnj->bmni", R, pts) + poses[..., None, :3]
    assert torch.allclose(out, ref, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(vec3)
def test_so3_exp_matches_matrix_exponential(w):
    omega = torch.tensor(w, dtype=F64)
    R = se3.quat_to_matrix(se3.so3_exp(omega))
    assert torch.allclose(R, torch.linalg.matrix_exp(hat(omega)), atol=1e-12)
    assert torch.allclose(se3.so3_exp(omega).norm(), torch.ones((), dtype=F64), atol=1e-14)


@settings(max_examples=60, deadline=None)
@given(vec3, vec3)
def test_se3_exp_matches_matrix_exponential(v, w):
    xi = torch.tensor(v + w, dtype=F64)
    T = torch.zeros(4, 4, dtype=F64)
    T[:3, :3] = hat(xi[3:])
    T[:3, 3] = xi[:3]
    ref = torch.linalg.matrix_exp(T)
    pose = se3.se3_exp(xi)
    assert torch.allclose(pose[:3], ref[:3, 3], atol=1e-12)
    assert torch.allclose(se3.quat_to_matrix(pose[3:]), ref[:3, :3], atol=1e-12)


@settings(max_examples=80, deadline=None)
@given(vec3, st.lists(st.floats(-1, 1), min_size=3, max_size=3), st.floats(0.0, math.pi - 1e-6))
def test_se3_log_exp_round_trip(v, axis, angle):
    axis = torch.tensor(axis, dtype=F64)
    axis = axis / axis.norm() if axis.norm() > 1e-3 else torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    xi = torch.cat((torch.tensor(v, dtype=F64), angle * axis))
    assert torch.allclose(se3.se3_log(se3.se3_exp(xi)), xi, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(pose_strategy)
def test_se3_exp_log_round_trip(pose):
    back = se3.se3_exp(se3.se3_log(pose))
    assert torch.allclose(back[:3], pose[:3], atol=1e-12)
    assert se3.angle_between(back[3:], pose[3:]) < 1e-7


def test_logs_treat_q_and_minus_q_alike():
    poses = random_poses(20, 7)
    flipped = torch.cat((poses[:, :3], -poses[:, 3:]), -1)
    assert torch.allclose(se3.so3_log(poses[:, 3:]), se3.so3_log(flipped[:, 3:]), atol=1e-14)
    assert torch.allclose(se3.se3_log(poses), se3.se3_log(flipped), atol=1e-14)
    assert (se3.so3_log(poses[:, 3:]).norm(dim=-1) <= math.pi + 1e-12).all()


SMALL = [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 1e-2, 0.0105, 0.011, 0.3]  # 0.011 straddles the float64 threshold


@pytest.mark.parametrize("scale", SMALL)
def test_gradcheck_near_zero(scale):
    g = torch.Generator().manual_seed(int(scale * 1e6) % 1000)
    direction = torch.randn(6, generator=g, dtype=F64)
    xi = (torch.cat((direction[:3], scale * direction[3:] / direction[3:].norm()))).requires_grad_()
    assert torch.autograd.gradcheck(se3.se3_exp, (xi,))
    assert torch.autograd.gradcheck(se3.so3_exp, (xi[3:].detach().requires_grad_(),))
    pose = se3.se3_exp(xi).detach().requires_grad_()
    assert torch.autograd.gradcheck(se3.se3_log, (pose,))
    assert torch.autograd.gradcheck(se3.so3_log, (pose[3:].detach().requires_grad_(),))


@pytest.mark.parametrize("angle", [1e-9, 1e-6, 1e-3, 9e-3, 0.0105, 0.0115, 0.05, 1.0, 3.0])
def test_exp_log_against_high_precision(angle):
    """Series and closed forms against 30-digit matrix exponentials (mpmath), either side of the threshold."""
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 30
    g = torch.Generator().manual_seed(int(angle * 1e9) % 997)
    direction = torch.randn(6, generator=g, dtype=F64)
    xi = torch.cat((direction[:3], angle * direction[3:] / direction[3:].norm()))
    v, w = [mpmath.mpf(float(c)) for c in xi[:3]], [mpmath.mpf(float(c)) for c in xi[3:]]
    twist = mpmath.matrix(
        [[0, -w[2], w[1], v[0]], [w[2], 0, -w[0], v[1]], [-w[1], w[0], 0, v[2]], [0, 0, 0, 0]]
    )
    T = torch.tensor(mpmath.expm(twist).tolist(), dtype=F64)
    pose = se3.se3_exp(xi)
    assert torch.allclose(pose[:3], T[:3, 3], atol=1e-15, rtol=0)
    assert torch.allclose(se3.quat_to_matrix(pose[3:]), T[:3, :3], atol=1e-15, rtol=0)
    exact_pose = torch.cat((T[:3, 3], se3.matrix_to_quat(T[:3, :3])))
    assert torch.allclose(se3.se3_log(exact_pose), xi, atol=1e-15, rtol=0)


def test_exact_derivatives_at_zero():
    omega = torch.zeros(3, dtype=F64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(se3.so3_exp, omega)
    assert torch.allclose(jac, torch.cat((torch.zeros(1, 3, dtype=F64), 0.5 * torch.eye(3, dtype=F64))))
    q = torch.tensor([1.0, 0, 0, 0], dtype=F64)
    jac = torch.autograd.functional.jacobian(se3.so3_log, q)
    assert torch.allclose(jac, torch.cat((torch.zeros(3, 1, dtype=F64), 2 * torch.eye(3, dtype=F64)), 1))
    jac = torch.autograd.functional.jacobian(se3.se3_log, se3.identity(dtype=F64))
    assert torch.allclose(jac[:3, :3], torch.eye(3, dtype=F64)) and torch.isfinite(jac).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_finite_at_zero_and_half_turn(dtype):
    for f, x in [
        (se3.so3_exp, torch.zeros(3, dtype=dtype)),
        (se3.se3_exp, torch.zeros(6, dtype=dtype)),
        (se3.so3_log, torch.tensor([1.0, 0, 0, 0], dtype=dtype)),
        (se3.so3_log, torch.tensor([0.0, 0, 0, 1], dtype=dtype)),  # half turn
        (se3.so3_log, torch.tensor([-1e-9, 0.6, 0.8, 0], dtype=dtype)),
        (se3.se3_log, se3.identity(dtype=dtype)),
        (se3.se3_log, torch.tensor([0.1, 0.2, 0.3, 0.0, 1.0, 0.0, 0.0], dtype=dtype)),
    ]:
        x = x.clone().requires_grad_()
        jac = torch.autograd.functional.jacobian(f, x)
        assert torch.isfinite(jac).all(), f.__name__


def test_so3_log_near_half_turn():
    for d in [1e-2, 1e-3]:
        omega = torch.tensor([0.0, 0.6, 0.8], dtype=F64) * (math.pi - d)
        q = se3.so3_exp(omega).requires_grad_()
        assert torch.allclose(se3.so3_log(q), omega, atol=1e-12)
        assert torch.autograd.gradcheck(se3.so3_log, (q,))
        pose = torch.cat((torch.tensor([0.1, -0.2, 0.3], dtype=F64), q.detach())).requires_grad_()
        assert torch.autograd.gradcheck(se3.se3_log, (pose,))


def test_float32_round_trip_and_dtype():
    xi = torch.randn(100, 6, dtype=F64) * torch.tensor([1, 1, 1, 0.5, 0.5, 0.5], dtype=F64)
    out = se3.se3_log(se3.se3_exp(xi.float()))
    assert out.dtype == torch.float32
    assert torch.allclose(out.double(), xi, atol=1e-5)
    tiny = torch.tensor([1e-4, 0.2, -0.1, 1e-6, -2e-6, 3e-6])
    assert torch.allclose(se3.se3_log(se3.se3_exp(tiny)), tiny, atol=1e-7)


def test_retract():
    poses = random_poses(30, 8)
    delta = torch.randn(30, 6, dtype=F64) * 0.3
    out = se3.retract(poses, delta)
    assert torch.allclose(out[:, :3], poses[:, :3] + delta[:, :3])
    assert torch.allclose(out[:, 3:].norm(dim=-1), torch.ones(30, dtype=F64), atol=1e-14)
    R_ref = torch.linalg.matrix_exp(hat(delta[:, 3:])) @ se3.quat_to_matrix(poses[:, 3:])
    assert torch.allclose(se3.quat_to_matrix(out[:, 3:]), R_ref, atol=1e-12)
    assert torch.allclose(se3.retract(poses, torch.zeros(30, 6, dtype=F64)), poses, atol=1e-15)
    # many small steps keep the quaternion unit
    pose = poses[:1]
    for _ in range(1000):
        pose = se3.retract(pose, torch.full((1, 6), 1e-3, dtype=F64))
    assert abs(float(pose[0, 3:].norm()) - 1) < 1e-14


@settings(max_examples=50, deadline=None)
@given(coord, coord, st.floats(-math.pi + 1e-6, math.pi), st.floats(-1, 1))
def test_se2_round_trip(x, y, theta, z):
    planar = torch.tensor([x, y, theta], dtype=F64)
    pose = se3.se2_to_se3(planar, z=z)
    assert pose[2] == z
    assert torch.allclose(se3.se3_to_se2(pose), planar, atol=1e-12)
    R = se3.quat_to_matrix(pose[3:])
    c, s = math.cos(theta), math.sin(theta)
    ref = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert torch.allclose(R, ref.to(F64), atol=1e-12)
    assert torch.allclose(se3.yaw(pose), torch.tensor(theta, dtype=F64), atol=1e-12)


def test_yaw_ignores_tilt_free_parts():
    yaw_pose = se3.se2_to_se3(torch.tensor([0.0, 0.0, 0.7], dtype=F64))
    assert torch.allclose(se3.yaw(yaw_pose), torch.tensor(0.7, dtype=F64))
    roll = torch.tensor([0.0, 0, 0, math.cos(0.2), math.sin(0.2), 0, 0], dtype=F64)
    assert torch.allclose(se3.yaw(se3.compose(yaw_pose, roll)), torch.tensor(0.7, dtype=F64), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(pose_strategy, pose_strategy)
def test_angle_between(a, b):
    qa, qb = a[3:], b[3:]
    angle = se3.angle_between(qa, qb)
    ref = se3.so3_log(se3.quat_multiply(se3.quat_conjugate(qa), qb)).norm()
    assert 0 <= angle <= math.pi
    assert torch.allclose(angle, ref, atol=1e-10)
    assert torch.allclose(se3.angle_between(qb, qa), angle, atol=1e-12)
    assert torch.allclose(se3.angle_between(qa, -qb), angle, atol=1e-12)


def test_angle_between_gradients_finite_at_equal_rotations():
    q = random_poses(5, 9)[:, 3:]
    for other in (q, -q):
        qa = q.clone().requires_grad_()
        angle = se3.angle_between(qa, other)
        (grad,) = torch.autograd.grad(angle.sum(), qa)
        assert torch.isfinite(grad).all()
        assert torch.allclose(angle, torch.zeros(5, dtype=F64), atol=1e-7)
    qa = torch.tensor([1.0, 0, 0, 0], dtype=F64, requires_grad=True)
    qb = se3.so3_exp(torch.tensor([0.0, 0.0, 0.5], dtype=F64))
    assert torch.allclose(se3.angle_between(qa, qb), torch.tensor(0.5, dtype=F64))
    assert torch.autograd.gradcheck(se3.angle_between, (qa, qb.requires_grad_()))


@pytest.mark.parametrize("shapes", [((5, 2, 3, 3), (3, 7)), ((5, 2, 3, 3), (5, 1, 3, 3)), ((4, 6, 3), (4, 3, 3)),
                                    ((5, 3, 40), (5, 40, 3))])
def test_traced_small_matmul_and_cross_match_the_eager_ones_with_gradients(shapes):
    """Under torch.compile the small products and the cross product are spelled out (so inductor fuses them); they
    must equal the eager matmul and aten's cross, values and gradients, to rounding."""
    g = torch.Generator().manual_seed(3)
    a, b = (torch.randn(shape, generator=g, dtype=F64, requires_grad=True) for shape in shapes)
    u, v = (torch.randn(4, 6, 3, generator=g, dtype=F64, requires_grad=True) for _ in range(2))

    def products(a, b, u, v):
        return se3.small_matmul(a, b), se3._cross(u, v)

    traced = torch.compile(products, backend="eager", fullgraph=True)(a, b, u, v)
    eager = products(a, b, u, v)
    for t, e, inputs in zip(traced, eager, ((a, b), (u, v))):
        torch.testing.assert_close(t, e, rtol=0, atol=1e-13)
        weights = torch.randn(e.shape, generator=g, dtype=F64)
        for gt, ge in zip(torch.autograd.grad((t * weights).sum(), inputs), torch.autograd.grad((e * weights).sum(), inputs)):
            torch.testing.assert_close(gt, ge, rtol=0, atol=1e-12)
    assert torch.equal(eager[0], a @ b) and torch.equal(eager[1], torch.linalg.cross(u, v))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("shape", [(4,), (7, 4), (5, 3, 4), (0, 4)])
def test_the_traced_rotation_matrix_equals_the_eager_one_bit_for_bit_with_gradients_to_rounding(dtype, shape):
    """``quat_to_matrix`` gathers from an outer product in eager and spells the entries out under torch.compile: the
    same values bit for bit, unnormalised quaternions included, and the same gradients to rounding."""
    g = torch.Generator().manual_seed(5)
    q = (3.0 * torch.randn(shape, generator=g, dtype=dtype)).requires_grad_()
    traced = torch.compile(se3.quat_to_matrix, backend="eager", fullgraph=True)(q)
    eager = se3.quat_to_matrix(q)
    assert eager.shape == (*shape[:-1], 3, 3) and eager.dtype == dtype
    assert torch.equal(traced, eager)
    if q.numel():
        weights = torch.randn(eager.shape, generator=g, dtype=dtype)
        (grad_traced,) = torch.autograd.grad((traced * weights).sum(), q)
        (grad_eager,) = torch.autograd.grad((eager * weights).sum(), q)
        torch.testing.assert_close(grad_eager, grad_traced, rtol=0, atol=20 * torch.finfo(dtype).eps * grad_traced.abs().max().item())


def test_a_rotation_matrix_first_made_in_inference_mode_still_takes_gradients_after_it():
    """The eager form's tables are made once, on the first call; made in inference mode they would be inference
    tensors, which a product that needs gradients cannot save (a planner's first call may run in inference mode)."""
    se3._rotation_tables.cache_clear()
    q = random_poses(3, 6)[:, 3:]
    with torch.inference_mode():
        first = se3.quat_to_matrix(q)
    leaf = q.clone().requires_grad_()
    (grad,) = torch.autograd.grad(se3.quat_to_matrix(leaf).sum(), leaf)
    assert torch.equal(se3.quat_to_matrix(q), first) and torch.isfinite(grad).all()
