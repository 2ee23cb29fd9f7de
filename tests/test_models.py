"""The vehicle models (``jaxquat/mechanics/models.py``): each field against an independent NumPy one,
the gyrostat's conservation laws by autodiff (which is what checks the derived equations),
the wheel limits, gradients, jit/vmap and bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from jax.test_util import check_grads

import jaxquat as jq
from helpers import DTYPE, NP_DTYPE, X64, assert_close, seeds

TOL = 1e-12 if X64 else 2e-5
N = 16  # the fixed batch every hypothesis example draws, so each jitted function compiles once
AXES = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]]) / np.array([[1], [1], [1], [3**0.5]])
J = np.array([[10.0, 0.3, -0.2], [0.3, 8.0, 0.1], [-0.2, 0.1, 6.0]])


def _np_rotation(q):
    a, b, c, d = q / np.linalg.norm(q)
    return np.array(
        [
            [a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
            [2 * (b * c + a * d), a * a - b * b + c * c - d * d, 2 * (c * d - a * b)],
            [2 * (b * d - a * c), 2 * (c * d + a * b), a * a - b * b - c * c + d * d],
        ]
    )


def _np_qdot(q, w):
    return 0.5 * np.concatenate([[-q[1:] @ w], q[0] * w + np.cross(q[1:], w)])


def _draw(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(N, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return rng, q.astype(NP_DTYPE)


def _thrust_torque(t, y, args):
    return args["thrust"], args["torque"]


def _wheels(t, y, args):
    return args["u"], args["external"]


QUAD = jq.Quadrotor(1.5, jnp.asarray(np.diag([0.02, 0.03, 0.05]), DTYPE), _thrust_torque, drag=0.2, gravity=9.81)
CRAFT = jq.ReactionWheelSpacecraft(jnp.asarray(J, DTYPE), jnp.asarray(AXES, DTYPE), _wheels)
quad_field = jax.jit(jax.vmap(lambda y, a: QUAD(0.0, y, a)))
craft_field = jax.jit(jax.vmap(lambda y, a: CRAFT(0.0, y, a)))


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_quadrotor_field_against_numpy(seed):
    rng, q = _draw(seed)
    y = {"r": rng.normal(size=(N, 3)), "v": rng.normal(size=(N, 3)), "q": q, "w": rng.normal(size=(N, 3))}
    args = {"thrust": rng.uniform(0, 20, size=N), "torque": rng.normal(size=(N, 3))}
    out = quad_field(*jax.tree.map(lambda x: jnp.asarray(x, DTYPE), (y, args)))
    inertia = np.array([0.02, 0.03, 0.05])
    for i in range(N):
        r = _np_rotation(q[i].astype(np.float64))
        accel = args["thrust"][i] / 1.5 * r[:, 2] - [0, 0, 9.81] - 0.2 * y["v"][i]
        wdot = (args["torque"][i] - np.cross(y["w"][i], inertia * y["w"][i])) / inertia
        assert_close(out["v"][i], accel, tol=TOL * 20, what="v'")
        assert_close(out["w"][i], wdot, tol=TOL * 100, what="w'")
        assert_close(out["q"][i], _np_qdot(q[i], y["w"][i]), tol=TOL, what="q'")
        assert_close(out["r"][i], y["v"][i], tol=TOL, what="r'")


@settings(max_examples=5, deadline=None)
@given(seeds)
def test_gyrostat_field_against_numpy_and_its_conservation_laws(seed):
    """J w' = M - A u - w x (J w + A h), h' = u against NumPy; then by jvp along the field:
    d/dt R(q) H = R(q) M (so torque-free, any wheel torque keeps the inertial momentum) and,
    with u = 0 and M = 0, d/dt (1/2 w.J w) = 0."""
    rng, q = _draw(seed)
    y = {"q": q, "w": rng.normal(size=(N, 3)), "h": rng.normal(size=(N, 4))}
    args = {"u": rng.normal(size=(N, 4)), "external": rng.normal(size=(N, 3))}
    y, args = jax.tree.map(lambda x: jnp.asarray(x, DTYPE), (y, args))
    out = craft_field(y, args)
    for i in range(N):
        w, h, u, m = (np.asarray(x[i], np.float64) for x in (y["w"], y["h"], args["u"], args["external"]))
        wdot = np.linalg.solve(J, m - AXES.T @ u - np.cross(w, J @ w + AXES.T @ h))
        assert_close(out["w"][i], wdot, tol=TOL * 10, what="w'")
        assert_close(out["h"][i], u, tol=TOL, what="h'")
    rate = _momentum_rate(y, args)
    assert_close(rate, jq.rotate(y["q"], args["external"]), tol=TOL * 10, what="d/dt R(q) H")
    still = dict(args, u=jnp.zeros_like(args["u"]), external=jnp.zeros_like(args["external"]))
    assert float(jnp.abs(_energy_rate(y, still)).max()) < TOL * 10


@jax.jit
@jax.vmap
def _momentum_rate(y, args):
    return jax.jvp(CRAFT.momentum, (y,), (CRAFT(0.0, y, args),))[1]


@jax.jit
@jax.vmap
def _energy_rate(y, args):
    def energy(y):  # full precision: on a GPU the default lets float32 products run in TF32
        jw = jnp.dot(jnp.asarray(J, y["w"].dtype), y["w"], precision="highest")
        return 0.5 * jnp.dot(y["w"], jw, precision="highest")

    return jax.jvp(energy, (y,), (CRAFT(0.0, y, args),))[1]


def test_wheel_limits_clip_torque_and_stop_at_the_momentum_limit():
    craft = jq.ReactionWheelSpacecraft(
        jnp.asarray(J, DTYPE),
        jnp.asarray(AXES, DTYPE),
        _wheels,
        wheel_torque_limit=0.1,
        wheel_momentum_limit=jnp.asarray([1.0, 1, 1, 2], DTYPE),
    )
    u = jnp.asarray([0.5, -0.5, 0.05, 0.3], DTYPE)
    h = jnp.asarray([1.0, 1.0, -1.5, 0.5], DTYPE)
    # wheel 0 at its limit and pushed further: stopped; wheel 1 at its limit, pushed back: clipped
    # only; wheel 2 beyond its limit but pushed back; wheel 3 below its limit: clipped
    assert_close(craft.wheel_torque(u, h), jnp.asarray([0.0, -0.1, 0.05, 0.1], DTYPE), tol=TOL)
    y = {"q": jnp.asarray([1.0, 0, 0, 0], DTYPE), "w": jnp.zeros(3, DTYPE), "h": h}
    out = craft(0.0, y, {"u": u, "external": jnp.zeros(3, DTYPE)})
    assert_close(out["h"], craft.wheel_torque(u, h), tol=TOL)


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_in_state_and_parameters():
    """check_grads (both modes, order 1) of both fields in the state and in the parameters,
    at the identity and at a 180-degree attitude."""
    args = {"thrust": jnp.asarray(14.0), "torque": jnp.asarray([0.01, 0.0, -0.02])}
    # jitted: eager, its derivatives ran as about 75 single-operation compilations (session 41)
    quadrotor = jax.jit(
        lambda y, m: jq.Quadrotor(m, jnp.diag(jnp.asarray([0.02, 0.03, 0.05])), _thrust_torque)(0.0, y, args)
    )
    for q in ([1.0, 0, 0, 0], [0.0, 0, 1, 0]):
        y = {
            "r": jnp.zeros(3),
            "v": jnp.asarray([0.1, 0.2, 0.3]),
            "q": jnp.asarray(q),
            "w": jnp.asarray([1.0, -2, 0.5]),
        }
        check_grads(quadrotor, (y, jnp.asarray(1.5)), order=1, modes=("fwd", "rev"))
        yc = {"q": jnp.asarray(q), "w": jnp.asarray([0.1, -0.2, 0.05]), "h": jnp.asarray([0.3, -0.1, 0.2, 0.4])}
        argc = {"u": jnp.asarray([0.01, 0.02, -0.01, 0.0]), "external": jnp.asarray([0.0, 0.001, 0.0])}
        # under jit: check_grads perturbs J off symmetry, which the eager value check would reject
        check_grads(
            jax.jit(lambda y, j, argc=argc: jq.ReactionWheelSpacecraft(j, AXES, _wheels)(0.0, y, argc)),
            (yc, jnp.asarray(J)),
            order=1,
            modes=("fwd", "rev"),
        )


@pytest.mark.parametrize(
    "build, error, match",
    [
        (lambda: jq.Quadrotor(-1.0, np.eye(3), _thrust_torque), ValueError, "'mass'.*positive"),
        (lambda: jq.Quadrotor(1.0, np.eye(2), _thrust_torque), ValueError, "'inertia'.*3, 3"),
        (lambda: jq.Quadrotor(1.0, np.eye(3), "hover"), TypeError, "'control'"),
        (lambda: jq.ReactionWheelSpacecraft(J, np.ones((4, 2)), _wheels), ValueError, r"'axes'.*\(n, 3\)"),
        (
            lambda: jq.ReactionWheelSpacecraft(J, np.vstack([AXES[:3], np.zeros(3)]), _wheels),
            ValueError,
            "'axes'.*nonzero",
        ),
        (
            lambda: jq.ReactionWheelSpacecraft(J, AXES, _wheels, wheel_torque_limit=[1.0, 2.0]),
            ValueError,
            "'wheel_torque_limit'.*scalar or shaped",
        ),
        (
            lambda: jq.ReactionWheelSpacecraft(J, AXES, _wheels, wheel_momentum_limit=0.0),
            ValueError,
            "'wheel_momentum_limit'.*positive",
        ),
        (lambda: jq.ReactionWheelSpacecraft(-J, AXES, _wheels), ValueError, "'inertia'"),
    ],
)
def test_bad_input_names_the_argument(build, error, match):
    with pytest.raises(error, match=match):
        build()
