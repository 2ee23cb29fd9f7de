"""Lie-group calculus: plus/minus, the SO(3) Jacobians against autodiff of the exp/log
compositions they stand for (at zero, small, generic and near-pi angles), the adjoint,
and tangent-space optimisation with optax."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import given

import jaxquat as jq
from helpers import DTYPE, TOL, X64, assert_close, assert_same_rotation, random_quats, seeds

TOL_J = 1e-12 if X64 else 3e-6


def _phis():
    """Rotation vectors at 0, 1e-8, 1e-3, generic, and 1e-3 short of pi."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(6, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    mags = np.array([0.0, 1e-8, 1e-3, 0.7, 2.0, np.pi - 1e-3])
    return jnp.asarray(axes * mags[:, None], DTYPE)


PHIS = _phis()


def _jac_of(f):
    """Jacobian at e = 0 of e -> f(phi, e), for every phi row, in one compiled call."""
    return jax.jit(jax.vmap(lambda phi: jax.jacfwd(lambda e: f(phi, e))(jnp.zeros(3, DTYPE))))


@pytest.mark.parametrize(
    "name,composition",
    [
        # Exp(phi + e) = Exp(phi) Exp(J_r e): J_r = d/de Log(Exp(phi)* Exp(phi + e))
        ("right_jacobian", lambda phi, e: jq.minus(jq.from_rotvec(phi + e), jq.from_rotvec(phi))),
        # Exp(phi + e) = Exp(J_l e) Exp(phi)
        ("left_jacobian", lambda phi, e: jq.minus(jq.from_rotvec(phi + e), jq.from_rotvec(phi), "space")),
        # Log(Exp(phi) Exp(e)) = phi + J_r^-1 e
        ("right_jacobian_inverse", lambda phi, e: jq.to_rotvec(jq.plus(jq.from_rotvec(phi), e))),
        ("left_jacobian_inverse", lambda phi, e: jq.to_rotvec(jq.plus(jq.from_rotvec(phi), e, "space"))),
    ],
)
def test_jacobians_against_autodiff_of_exp_log(name, composition):
    expected = _jac_of(composition)(PHIS)
    got = getattr(jq, name)(PHIS)
    assert_close(got, expected, tol=TOL_J if name.endswith("jacobian") else 1e3 * TOL_J, what=name)


def test_jacobian_identities():
    jr, jl = jq.right_jacobian(PHIS), jq.left_jacobian(PHIS)
    eye = np.broadcast_to(np.eye(3), jr.shape)
    assert_close(jr @ jq.right_jacobian_inverse(PHIS), eye, tol=1e3 * TOL_J, what="J_r J_r^-1")
    assert_close(jl @ jq.left_jacobian_inverse(PHIS), eye, tol=1e3 * TOL_J, what="J_l J_l^-1")
    assert_close(jl, jq.to_matrix(jq.from_rotvec(PHIS)) @ jr, tol=10 * TOL_J, what="J_l = R J_r")
    assert_close(jl, jq.right_jacobian(-PHIS), tol=0, what="J_l(phi) = J_r(-phi)")
    assert_close(jq.right_jacobian(jnp.zeros((1, 3), DTYPE)), np.eye(3)[None], tol=0)


def test_jacobian_series_are_smooth_through_the_switch():
    """Second derivatives of J_r on both sides of the series/direct switch (|phi|^2 = 0.5) agree."""
    u = jnp.asarray([0.3, -0.5, 0.4], DTYPE) / np.sqrt(0.5)  # |u|^2 = 1
    f = lambda t: jq.right_jacobian_inverse(t * u)  # noqa: E731
    h = jax.jit(jax.jacfwd(jax.jacfwd(f)))
    below, above = h(jnp.asarray(np.sqrt(0.5) - 1e-7, DTYPE)), h(jnp.asarray(np.sqrt(0.5) + 1e-7, DTYPE))
    assert_close(below, above, tol=1e-5 if X64 else 1e-2, what="d2 J_r^-1 across the switch")


@given(seed=seeds)
def test_plus_minus_round_trip(seed):
    rng = np.random.default_rng(seed)
    q = jnp.asarray(random_quats(seed), DTYPE)
    d = rng.normal(size=(16, 3))
    d *= (rng.uniform(0, np.pi - 1e-3, 16) / np.linalg.norm(d, axis=-1))[:, None]
    d = jnp.asarray(d, DTYPE)
    for frame in ("body", "space"):
        assert_close(jq.minus(jq.plus(q, d, frame), q, frame), d, tol=1e3 * TOL, what=f"minus(plus) {frame}")
        assert_close(jq.norm(jq.plus(q, d, frame)), np.ones(16), tol=10 * TOL)
    # body and space perturbations are related by the adjoint
    assert_same_rotation(
        jq.plus(q, d), jq.plus(q, jnp.einsum("...ij,...j->...i", jq.adjoint(q), d), "space"), tol=100 * TOL
    )
    # minus is sign-invariant in both arguments
    assert_close(jq.minus(-q, q), np.zeros((16, 3)), tol=10 * TOL)


def test_plus_against_scipy():
    from scipy.spatial.transform import Rotation

    from helpers import from_scipy, to_scipy

    q = random_quats(5, 8, dtype=np.float64)
    d = np.random.default_rng(5).normal(size=(8, 3))
    ref = (Rotation.from_quat(to_scipy(q)) * Rotation.from_rotvec(d)).as_quat()
    assert_same_rotation(jq.plus(jnp.asarray(q, DTYPE), jnp.asarray(d, DTYPE)), from_scipy(ref), tol=100 * TOL)


def _loss(qq, tt, vv):
    return jnp.sum((jq.rotate(qq, vv) - jq.rotate(tt, vv)) ** 2)


@jax.jit
def _grads(q, target, v):
    g = jax.vmap(jax.grad(_loss))(q, target, v)
    along = {
        frame: jax.vmap(jax.grad(lambda d, qq, tt, vv, f=frame: _loss(jq.plus(qq, d, f), tt, vv)), (None, 0, 0, 0))(
            jnp.zeros(3, q.dtype), q, target, v
        )
        for frame in ("body", "space")
    }
    return g, along


@given(seed=seeds)
def test_tangent_gradient_is_the_derivative_along_plus(seed):
    q = jnp.asarray(random_quats(seed, 8), DTYPE)
    target = jnp.asarray(random_quats(seed + 1, 8, with_singular=False), DTYPE)
    v = jnp.asarray(np.random.default_rng(seed).normal(size=(8, 3)), DTYPE)
    g, along = _grads(q, target, v)
    for frame in ("body", "space"):
        assert_close(jq.tangent_gradient(q, g, frame), along[frame], tol=100 * TOL, what=f"tangent gradient {frame}")


def test_tangent_gradients_on_a_pytree():
    q = jnp.asarray(random_quats(2, 3), DTYPE)
    g = jnp.asarray(np.random.default_rng(2).normal(size=(3, 4)), DTYPE)
    params = {"attitudes": q, "gain": jnp.ones(2, DTYPE), "nested": (q[:1],)}
    grads = {"attitudes": g, "gain": jnp.full(2, 3.0, DTYPE), "nested": (g[:1],)}
    mask = {"attitudes": True, "gain": False, "nested": (True,)}
    out = jq.tangent_gradients(params, grads, mask)
    assert_close(out["attitudes"], jq.tangent_gradient(q, g), tol=0)
    assert_close(out["nested"][0], jq.tangent_gradient(q[:1], g[:1]), tol=0)
    assert_close(out["gain"], grads["gain"], tol=0)


def test_tangent_optimizer_fits_a_rotation_and_keeps_unit_norm():
    rng = np.random.default_rng(0)
    truth = jq.from_rotvec(jnp.asarray([1.0, -2.0, 0.5], DTYPE))
    b = jnp.asarray(rng.normal(size=(20, 3)), DTYPE)
    a = jq.rotate(truth, b)
    params = {"q": jq.identity((), DTYPE), "bias": jnp.zeros(3, DTYPE)}
    mask = {"q": True, "bias": False}

    def loss(p):
        return jnp.mean(jnp.sum((jq.rotate(p["q"], b) + p["bias"][None, :] - a) ** 2, -1))

    opt = jq.tangent_optimizer(optax.adam(optax.exponential_decay(0.1, 50, 0.5)), mask)
    assert isinstance(opt, optax.GradientTransformation)  # composes with optax.chain and the rest
    state = opt.init(params)
    with pytest.raises(ValueError, match="needs 'params'"):
        opt.update(params, state)

    @jax.jit
    def step(p, s):
        updates, s = opt.update(jax.grad(loss)(p), s, p)
        return jq.apply_tangent_updates(p, updates, mask), s

    for _ in range(600):
        params, state = step(params, state)
    # Adam's steps shrink with the decayed rate (0.1 / 2^12 at the end): 2e-6 rad is reached
    # in float64 from 2.3 rad away; examples/fit_rotation.py drives it to 1e-8 with more steps.
    assert float(jq.angle_between(params["q"], truth)) < (1e-5 if X64 else 1e-3)
    assert abs(float(jq.norm(params["q"])) - 1) < (1e-13 if X64 else 1e-6)
    assert float(jnp.abs(params["bias"]).max()) < (1e-5 if X64 else 1e-3)


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"argument 'delta' must be a 3-vector array shaped \(\.\.\., 3\)"):
        jq.plus(jq.identity(), jnp.zeros(4))
    with pytest.raises(ValueError, match="argument 'frame'"):
        jq.minus(jq.identity(), jq.identity(), "local")
    with pytest.raises(TypeError, match="GradientTransformation"):
        jq.tangent_optimizer(lambda g: g)
