"""Inertia tensors: point-mass construction, frame change, Chou's 4x4 inertia, validity checks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given

import jaxquat as jq
from helpers import DTYPE, TOL, X64, assert_close, random_inertias, random_quats, seeds

RTOL = 1e-12 if X64 else 1e-5


def _cloud(seed, n=7):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)), rng.uniform(0.1, 2.0, n)


def test_inertia_from_points_matches_the_definitions_of_chou_B1():
    r, m = _cloud(0)
    i = np.asarray(jq.inertia_from_points(jnp.asarray(r, DTYPE), jnp.asarray(m, DTYPE)), np.float64)
    x, y, z = r.T
    ixx, iyy, izz = (m * (y**2 + z**2)).sum(), (m * (z**2 + x**2)).sum(), (m * (x**2 + y**2)).sum()
    ixy, iyz, izx = (m * x * y).sum(), (m * y * z).sum(), (m * z * x).sum()
    ref = np.array([[ixx, -ixy, -izx], [-ixy, iyy, -iyz], [-izx, -iyz, izz]])
    assert_close(i / ref.max(), ref / ref.max(), tol=RTOL)
    # [C] (B3): integral of x^2 dm = (Iyy - Ixx + Izz) / 2, etc.
    assert_close((m * x**2).sum(), 0.5 * (iyy - ixx + izz), tol=1e-12)


@given(seed=seeds)
def test_rotate_inertia_is_the_inertia_of_the_rotated_body(seed):
    """[C] (C1): I0 = A I A^T equals the inertia of the rotated point cloud."""
    r, m = _cloud(seed % 1000)
    q = jnp.asarray(random_quats(seed, 1)[0], DTYPE)
    body = jq.inertia_from_points(jnp.asarray(r, DTYPE), jnp.asarray(m, DTYPE))
    space = jq.inertia_from_points(jq.rotate(jnp.broadcast_to(q, (7, 4)), jnp.asarray(r, DTYPE)), jnp.asarray(m, DTYPE))
    scale = float(jnp.abs(body).max())
    assert_close(jq.rotate_inertia(q, body) / scale, space / scale, tol=10 * RTOL)
    assert_close(jq.rotate_inertia(jq.conjugate(q), space) / scale, body / scale, tol=10 * RTOL)


def test_inertia_rate_chou_C4_against_autodiff():
    inertia = jnp.asarray(random_inertias(1, 1)[0], DTYPE)
    rv0, rv1 = jnp.asarray([0.2, -0.4, 0.9], DTYPE), jnp.asarray([0.7, 0.1, -0.3], DTYPE)

    def i_space(t):
        return jq.rotate_inertia(jq.from_rotvec(rv0 + t * rv1 + t * t * rv0[::-1]), inertia)

    t = jnp.asarray(0.3, DTYPE)
    q = jq.from_rotvec(rv0 + t * rv1 + t * t * rv0[::-1])
    qd = jax.jacfwd(lambda s: jq.from_rotvec(rv0 + s * rv1 + s * s * rv0[::-1]))(t)
    ws = jq.omega_from_qdot(q, qd, "space")
    assert_close(jq.inertia_rate(i_space(t), ws), jax.jacfwd(i_space)(t), tol=50 * TOL)


def test_quaternion_inertia_chou_B2_B5():
    r, m = _cloud(3)
    rq = jnp.asarray(np.concatenate([np.zeros((7, 1)), r], -1), DTYPE)  # pure quaternions (0, r)
    integrand = jnp.sum(rq * rq, -1)[:, None, None] * jnp.eye(4, dtype=DTYPE)[None] - rq[:, :, None] * rq[:, None, :]
    direct = jnp.sum(jnp.asarray(m, DTYPE)[:, None, None] * integrand, 0)  # [C] (B2), first form
    e = jq.rate_matrix(rq, "space")  # E-plus of a pure quaternion
    via_e = jnp.sum(jnp.asarray(m, DTYPE)[:, None, None] * (jnp.swapaxes(e, -1, -2) @ e), 0)  # [C] (B2), E^T E form
    i3 = jq.inertia_from_points(jnp.asarray(r, DTYPE), jnp.asarray(m, DTYPE))
    i4 = jq.quaternion_inertia(i3)
    s = float(jnp.abs(direct).max())
    assert_close(i4 / s, direct / s, tol=RTOL)
    assert_close(via_e / s, direct / s, tol=RTOL)
    assert_close(i4[0, 0], 0.5 * jnp.trace(i3), tol=RTOL * s)  # k = tr/2, [C] (B4)


def test_valid_tensors_pass_and_are_returned_unchanged():
    inertia = jnp.asarray(random_inertias(2), DTYPE)
    assert bool(jnp.all(jq.is_valid_inertia(inertia)))
    assert jq.check_inertia(inertia) is not None
    flat_plate = jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE))  # I3 = I1 + I2 exactly: valid
    assert bool(jq.is_valid_inertia(flat_plate))


BAD = {
    "not symmetric": ([[2.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0]], "not symmetric"),
    "singular": ([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "not positive definite"),
    "negative": ([[-1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 2.0]], "not positive definite"),
    "triangle": ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.5]], "triangle inequality"),
    "nan": ([[1.0, 0.0, 0.0], [0.0, np.nan, 0.0], [0.0, 0.0, 1.0]], "non-finite"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_tensors_raise_named_errors_and_fail_the_jit_check(case):
    matrix, message = BAD[case]
    batch = np.stack([np.diag([1.0, 2.0, 2.5]), matrix, np.eye(3)])
    with pytest.raises(ValueError, match=rf"argument 'inertia' at batch index \(1,\) .*{message}"):
        jq.check_inertia(jnp.asarray(batch, DTYPE))
    valid = jax.jit(jq.is_valid_inertia)(jnp.asarray(batch, DTYPE))
    assert valid.tolist() == [True, False, True]
    # the dynamics functions refuse it eagerly, naming the argument
    with pytest.raises(ValueError, match="argument 'inertia'"):
        jq.angular_acceleration(jq.identity(3, DTYPE), jnp.ones((3, 3), DTYPE), jnp.asarray(batch, DTYPE))


def test_the_eager_check_agrees_with_the_jit_check_at_each_boundary():
    """check_inertia passes clearly valid concrete tensors in NumPy (no compilation on a first
    call) and leaves the rest to the jitted is_valid_inertia; its verdict must be the jitted
    one, tensor by tensor, on tensors placed around each condition's threshold (relative offsets
    from -4 to 4 tolerances: the triangle inequality, positive definiteness, symmetry; also
    rotated off the principal axes). NumPy's verdict alone differed at one tensor in float32
    (an ulp of the eigenvalues); the margin must pass every tensor far from the thresholds."""
    from jaxquat.mechanics.inertia import _clearly_valid, _default_rtol, _is_valid_concrete

    rtol = _default_rtol(jnp.dtype(DTYPE))
    offsets = np.linspace(-4.0, 4.0, 33) * rtol
    rng = np.random.default_rng(7)
    tensors = []
    for d in offsets:
        tensors.append(np.diag([1.0, 2.0, 3.0 * (1 + d)]))  # I3 = (I1 + I2)(1 + d)
        tensors.append(np.diag([3.0 * (1 + d) * rtol, 2.0, 3.0]))  # I1 = (1 + d) rtol I3
        a = np.diag([1.0, 2.0, 2.5])
        a[0, 1] += 2.5 * rtol * (1 + d)  # |I - I^T| = (1 + d) rtol s
        tensors.append(a)
    r = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    tensors += [r @ t @ r.T for t in tensors[: len(offsets) * 2]]
    batch = jnp.asarray(np.stack(tensors), DTYPE)
    compiled = np.asarray(jax.jit(jq.is_valid_inertia)(batch))
    assert 0 < int(compiled.sum()) < len(tensors)  # both verdicts occur
    assert _is_valid_concrete(batch, rtol).tolist() == compiled.tolist()
    clear = _clearly_valid(batch, rtol)
    assert not np.any(clear & ~compiled)  # clearly valid is valid
    far = np.abs(offsets) >= 2 * rtol  # two tolerances or more from the threshold
    assert clear[: 3 * len(offsets)].reshape(-1, 3)[far & (offsets < 0), 0].all()  # triangle: the valid side
    assert _clearly_valid(jnp.asarray(random_inertias(16), DTYPE), rtol).all()
    first_bad = int(np.argmin(compiled))
    with pytest.raises(ValueError, match=rf"batch index \({first_bad},\)"):
        jq.check_inertia(batch)


def test_check_inertia_inside_jit_points_to_the_jit_helper():
    with pytest.raises(TypeError, match="is_valid_inertia"):
        jax.jit(jq.check_inertia)(jnp.eye(3, dtype=DTYPE))


def test_inertia_shape_errors():
    with pytest.raises(ValueError, match=r"argument 'inertia' must be an inertia tensor array shaped \(\.\.\., 3, 3\)"):
        jq.kinetic_energy(jq.identity((), DTYPE), jnp.zeros(3, DTYPE), jnp.ones(3, DTYPE))
    with pytest.raises(ValueError, match="argument 'masses'"):
        jq.inertia_from_points(jnp.zeros((5, 3)), jnp.ones(4))
