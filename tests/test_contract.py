"""The contract every public function keeps: jit/vmap/nested batching, dtypes,
finite and correct gradients (forward and reverse, against finite differences)
at random and singular points, and clear errors for bad input."""

from __future__ import annotations

import functools
import re

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from helpers import (
    DTYPE,
    X64,
    assert_close,
    central_difference_jacobian,
    jaxpr_equations,
    lowered_programs,
    on_device,
    random_inertias,
)

B = 12
RNG = np.random.default_rng(1234)
S = np.sqrt(0.5)


def _unit(a):
    a = np.asarray(a, np.float64)
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


# Points where the functions are smooth: finite differences are valid here. They
# include the identity, a 1e-8 rotation, rotations just short of 180 degrees and
# Euler angles 0.05 rad from gimbal lock.
SMOOTH_Q = _unit(
    np.concatenate(
        [
            [[1, 0, 0, 0], [np.cos(5e-9), np.sin(5e-9), 0, 0], [1e-3, 1, 0, 0], [1e-3, 0, S, S]],
            [[np.cos(np.pi / 4 - 0.025), 0, np.sin(np.pi / 4 - 0.025), 0]],  # pitch 90 - 2.9 deg
            RNG.normal(size=(B - 5, 4)),
        ]
    )
)
# Exactly singular points: gradients must be finite (not NaN/inf) and forward == reverse.
SINGULAR_Q = _unit(
    [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, S, S], [S, 0, S, 0], [-1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]]
    + [[S, 0, -S, 0]] * (B - 6)
)


def _args(kind: str, q: np.ndarray):
    n = len(q)
    rng = np.random.default_rng(n)
    if kind == "q":
        return q
    if kind == "p":
        return _unit(rng.normal(size=q.shape))
    if kind == "v":
        return rng.normal(size=(n, 3))
    if kind == "m":
        return np.asarray(jq.to_matrix(jnp.asarray(q)))
    if kind == "t":
        return rng.uniform(0.1, 0.9, n)
    if kind == "r":
        return np.asarray(jq.to_rotvec(jnp.asarray(q)))
    if kind == "angles":
        return np.stack([rng.uniform(-3, 3, n), rng.uniform(-1.5, 1.5, n), rng.uniform(-3, 3, n)], -1)
    if kind == "qn":
        return _unit(q[:, None, :] + 0.3 * rng.normal(size=(n, 5, 4)))
    if kind == "vn":
        return rng.normal(size=(n, 5, 3))
    if kind == "an":
        # a_i = R b_i + noise so the Wahba problem is well posed
        b = _args("vn", q)
        return np.asarray(jq.rotate(jnp.asarray(q)[:, None, :], jnp.asarray(b))) + 0.05 * rng.normal(size=b.shape)
    if kind == "wn":
        return rng.uniform(0.5, 1.5, (n, 5))
    if kind == "p3":
        return np.asarray(jq.to_mrp(jnp.asarray(q)))
    if kind == "w":  # angular velocity / acceleration
        return np.random.default_rng(n + 100).normal(size=(n, 3))
    if kind == "qd":  # a rate tangent to q
        d = np.random.default_rng(n + 101).normal(size=(n, 4))
        return d - (d * q).sum(-1, keepdims=True) * q
    if kind in ("qdd", "f"):
        return np.random.default_rng(n + 102).normal(size=(n, 4))
    if kind == "J":
        return random_inertias(n, n, np.float64)
    if kind == "pts":
        return np.random.default_rng(n + 103).normal(size=(n, 5, 3))
    if kind == "ms":
        return np.random.default_rng(n + 104).uniform(0.5, 2.0, (n, 5))
    if kind == "r3":
        return 3.0 * _unit(np.random.default_rng(n + 105).normal(size=(n, 3)))
    raise KeyError(kind)


# name -> (function, argument kinds, differentiable argument index or None)
REGISTRY = {
    "multiply": (jq.multiply, ["q", "p"], 0),
    "conjugate": (jq.conjugate, ["q"], 0),
    "inverse": (jq.inverse, ["q"], 0),
    "norm": (jq.norm, ["q"], 0),
    "normalize": (jq.normalize, ["q"], 0),
    "exp": (jq.exp, ["r4"], 0),
    "log": (jq.log, ["q"], 0),
    "power": (jq.power, ["q", "t"], 0),
    "left_matrix": (jq.left_matrix, ["q"], 0),
    "right_matrix": (jq.right_matrix, ["q"], 0),
    "rotate": (jq.rotate, ["q", "v"], 0),
    "canonicalize": (jq.canonicalize, ["q"], 0),
    "to_matrix": (jq.to_matrix, ["q"], 0),
    "from_matrix": (jq.from_matrix, ["m"], 0),
    "from_matrix_nearest": (lambda m: jq.from_matrix(m, nearest=True), ["m"], 0),
    "to_rotvec": (jq.to_rotvec, ["q"], 0),
    "from_rotvec": (jq.from_rotvec, ["r"], 0),
    "to_axis_angle": (jq.to_axis_angle, ["q"], 0),
    "from_axis_angle": (jq.from_axis_angle, ["v", "t"], 1),
    "to_mrp": (jq.to_mrp, ["q"], 0),
    "from_mrp": (jq.from_mrp, ["p3"], 0),
    "to_euler_xyz": (lambda q: jq.to_euler(q, "xyz"), ["q"], 0),
    "to_euler_ZXZ": (lambda q: jq.to_euler(q, "ZXZ"), ["q"], 0),
    "from_euler_ZYX": (lambda a: jq.from_euler(a, "ZYX"), ["angles"], 0),
    "angle": (jq.angle, ["q"], 0),
    "angle_between": (jq.angle_between, ["q", "p"], 0),
    "slerp": (jq.slerp, ["q", "p", "t"], 0),
    "slerp_t": (jq.slerp, ["p", "q", "t"], 2),
    "mean": (jq.mean, ["qn", "wn"], 0),
    "align_vectors": (jq.align_vectors, ["an", "vn", "wn"], 0),
    # attitude determination: tests/test_determination.py has the values
    "quest": (jq.quest, ["vn", "an", "wn"], 1),
    "triad": (jq.triad, ["v", "w", "r3", "v"], 2),
    "attitude_covariance": (jq.attitude_covariance, ["vn", "ms"], 0),
    # skew, kinematics
    "hat": (jq.hat, ["v"], 0),
    "vee": (jq.vee, ["m"], 0),
    "rate_matrix_body": (lambda q: jq.rate_matrix(q, "body"), ["q"], 0),
    "rate_matrix_space": (lambda q: jq.rate_matrix(q, "space"), ["q"], 0),
    "qdot_from_omega_body": (lambda q, w: jq.qdot_from_omega(q, w, "body"), ["q", "w"], 0),
    "qdot_from_omega_space": (lambda q, w: jq.qdot_from_omega(q, w, "space"), ["q", "w"], 1),
    "omega_from_qdot_body": (lambda q, d: jq.omega_from_qdot(q, d, "body"), ["q", "qd"], 0),
    "omega_from_qdot_space": (lambda q, d: jq.omega_from_qdot(q, d, "space"), ["q", "qd"], 1),
    "qddot_from_alpha_body": (lambda q, d, a: jq.qddot_from_alpha(q, d, a, "body"), ["q", "qd", "w"], 0),
    "qddot_from_alpha_space": (lambda q, d, a: jq.qddot_from_alpha(q, d, a, "space"), ["q", "qd", "w"], 1),
    "alpha_from_qddot_body": (lambda q, d, dd: jq.alpha_from_qddot(q, d, dd, "body"), ["q", "qd", "qdd"], 0),
    "alpha_from_qddot_space": (lambda q, d, dd: jq.alpha_from_qddot(q, d, dd, "space"), ["q", "qd", "qdd"], 1),
    "matrix_rate": (lambda q, w: jq.matrix_rate(q, w, "space"), ["q", "w"], 0),
    "matrix_acceleration": (jq.matrix_acceleration, ["q", "w", "v"], 0),
    "point_velocity": (lambda q, w, r: jq.point_velocity(q, w, r, frame="space"), ["q", "w", "v"], 0),
    "point_acceleration": (lambda q, w, a, r: jq.point_acceleration(q, w, a, r, r, r), ["q", "w", "w", "v"], 0),
    # inertia, dynamics, torques
    "inertia_from_points": (jq.inertia_from_points, ["pts", "ms"], 0),
    "rotate_inertia": (jq.rotate_inertia, ["q", "J"], 0),
    "inertia_rate": (jq.inertia_rate, ["J", "w"], 0),
    "quaternion_inertia": (jq.quaternion_inertia, ["J"], 0),
    "angular_momentum": (lambda q, w, i: jq.angular_momentum(q, w, i, "space"), ["q", "w", "J"], 0),
    "kinetic_energy": (jq.kinetic_energy, ["q", "w", "J"], 2),
    "angular_acceleration": (lambda q, w, i, m: jq.angular_acceleration(q, w, i, m, "space"), ["q", "w", "J", "v"], 0),
    "angular_acceleration_inertia": (jq.angular_acceleration, ["q", "w", "J", "v"], 2),
    "inverse_dynamics": (jq.inverse_dynamics, ["q", "w", "v", "J"], 1),
    "euler_parameter_acceleration_body": (jq.euler_parameter_acceleration, ["q", "qd", "J", "v"], 0),
    "euler_parameter_acceleration_space": (
        lambda q, d, i, m: jq.euler_parameter_acceleration(q, d, i, m, "space"),
        ["q", "qd", "J", "v"],
        1,
    ),
    "euler_parameter_acceleration_inertia": (jq.euler_parameter_acceleration, ["q", "qd", "J", "v"], 2),
    "euler_parameter_torque": (jq.euler_parameter_torque, ["q", "qd", "qdd", "J"], 0),
    "euler_parameter_mass_matrix": (jq.euler_parameter_mass_matrix, ["q", "J"], 0),
    "euler_parameter_augmented_system": (jq.euler_parameter_augmented_system, ["q", "qd", "J", "v"], 0),
    "norm_constraint_multiplier": (jq.norm_constraint_multiplier, ["q", "qd", "J"], 1),
    "generalized_force": (lambda q, m: jq.generalized_force(q, m, "space"), ["q", "v"], 0),
    "torque_from_generalized_force": (jq.torque_from_generalized_force, ["q", "f"], 0),
    "gravity_gradient_torque": (jq.gravity_gradient_torque, ["q", "r3", "J"], 0),
    # Lie calculus, tangent gradients, squad
    "plus": (jq.plus, ["q", "r"], 1),
    "plus_space": (lambda q, d: jq.plus(q, d, "space"), ["q", "r"], 0),
    "minus": (jq.minus, ["q", "p"], 0),
    "minus_space": (lambda a, b: jq.minus(a, b, "space"), ["q", "p"], 1),
    "right_jacobian": (jq.right_jacobian, ["r"], 0),
    "right_jacobian_inverse": (jq.right_jacobian_inverse, ["r"], 0),
    "left_jacobian": (jq.left_jacobian, ["r"], 0),
    "left_jacobian_inverse": (jq.left_jacobian_inverse, ["r"], 0),
    "adjoint": (jq.adjoint, ["q"], 0),
    "tangent_gradient": (jq.tangent_gradient, ["q", "f"], 0),
    "squad_segment": (jq.squad_segment, ["q", "p", "q", "p", "t"], 0),
    "squad_control_points": (jq.squad_control_points, ["qn"], 0),
}

# Rows of SMOOTH_Q where a function has a genuine kink, so finite differences
# (step 1e-6) are not valid there: the cone of the angle within 1e-8 of the
# identity, gimbal lock of symmetric sequences at the identity and at 180
# degrees about x, and a tie between two Shepperd branches (from_matrix is
# smooth along SO(3) there but its off-manifold derivative depends on the branch).
FD_EXCLUDED_ROWS = {
    "angle": [0, 1],
    "to_axis_angle": [0, 1],
    "to_euler_ZXZ": [0, 1, 2],
    "from_matrix": [3],
}

# Functions with a genuine kink at some singular point; there we only require finiteness.
NONSMOOTH_AT_SINGULAR = {
    "minus",
    "minus_space",
    "squad_segment",
    "squad_control_points",
    "norm",
    "canonicalize",
    "to_rotvec",
    "to_axis_angle",
    "to_mrp",
    "to_euler_xyz",
    "to_euler_ZXZ",
    "angle",
    "angle_between",
    "log",
    "power",
    "slerp",
    "from_matrix",
}


# Functions returning the canonical unit quaternion (w >= 0) of a rotation: at a half turn, w = 0
# within half precision's rounding, and either sign is canonical.
UNIT_QUAT_OUTPUTS = {"align_vectors", "quest", "triad", "mean", "from_matrix"}


def _make(name, q):
    fn, kinds, diff = REGISTRY[name]
    args = []
    for k in kinds:
        if k == "r4":
            a = np.concatenate([np.zeros((len(q), 1)), _args("r", q) / 2], -1)
            a[:, 0] = np.linspace(-1, 1, len(q))
        else:
            a = _args(k, q)
        args.append(np.asarray(a))
    return fn, args, diff


def _leaves(out):
    return jax.tree_util.tree_leaves(out)


def _loss(fn, args, diff, weights):
    def loss(x):
        a = list(args)
        a[diff] = x
        return sum(jnp.sum(o * w) for o, w in zip(_leaves(fn(*a)), weights))

    return loss


NAMES = sorted(REGISTRY)


def _transformed(fn):
    """``fn`` under ``jit``, under ``vmap`` and on the batch reshaped to ``(3, 4, ...)``, in one
    compiled program (three programs of their own until session 36: the test's 79 cases with
    pytest's start-up took 30-34 s alone, now 25-26 s; float64, 2-core EPYC)."""

    def all_three(*args):
        nested = fn(*[a.reshape((3, 4) + a.shape[1:]) for a in args])
        return fn(*args), jax.vmap(fn)(*args), nested

    return jax.jit(all_three)


@pytest.mark.parametrize("name", NAMES)
def test_jit_vmap_and_nested_batching(name):
    """The eager call (its own compiled program) against the same function traced under ``jit``,
    mapped by ``vmap`` (one element at a time), and called on a nested batch ``(3, 4, ...)``."""
    fn, args, _ = _make(name, SMOOTH_Q)
    args = [on_device(a, DTYPE) for a in args]
    eager = fn(*args)
    jitted, mapped, nested = _transformed(fn)(*args)
    for e, j, m, n in zip(_leaves(eager), _leaves(jitted), _leaves(mapped), _leaves(nested)):
        assert e.dtype == DTYPE, f"{name} changed dtype to {e.dtype}"
        assert j.dtype == m.dtype == n.dtype == DTYPE, f"{name} changed dtype under a transformation"
        assert_close(j, e, tol=1e-12 if X64 else 1e-5, what=f"{name} jit")
        assert_close(m, e, tol=1e-12 if X64 else 1e-5, what=f"{name} vmap")
        # Nested batch (3, 4, ...) gives the same numbers as the flat batch.
        assert_close(np.asarray(n).reshape(e.shape), e, tol=1e-12 if X64 else 1e-5, what=f"{name} nested")


def test_an_argument_without_batch_axes_is_not_broadcast_to_the_batch():
    """``rotate``, ``angle_between``, ``power`` and ``slerp`` take an argument without batch axes
    (one vector for a batch of rotations, one rotation for a batch of vectors, one exponent, one
    start of the arcs) as it is: its components reach the kernel as scalars. Broadcast first, the
    argument was written to memory at the batch's size and read back (10^6 rotations, float32, one
    core: ``rotate(Q, v)`` eager 4.8-6.2 -> 2.7 ms and its gradient 16.5-17.1 -> 7.9-9.6 ms,
    ``angle_between(Q, q)`` eager 8.7-9.2 -> 4.1-5.6 ms, gradient 107-114 -> 53-78 ms). No value
    program broadcasts the argument to the batch (``slerp``'s gradient kernel does, inside its
    program); the values are those of the argument repeated for every row, and the argument's
    gradient is the sum of theirs. (``multiply``, ``plus``, ``minus`` and the other kernels formed
    from rows have it broadcast inside their program: the next test.)"""
    n = 7
    q = jq.random(jax.random.PRNGKey(5), (n,), DTYPE)
    v = jnp.asarray(RNG.normal(size=(n, 3)), DTYPE)
    t = jnp.asarray(RNG.uniform(0.1, 0.9, size=n), DTYPE)
    one_q, one_v = jq.random(jax.random.PRNGKey(8), (), DTYPE), v[0]
    calls = {  # name: (function of the shared argument, the shared argument)
        "rotate(Q, v)": (lambda a: jq.rotate(q, a), one_v),
        "rotate(q, V)": (lambda a: jq.rotate(a, v), one_q),
        "angle_between(Q, q)": (lambda a: jq.angle_between(q, a), one_q),
        "power(Q, t)": (lambda a: jq.power(q, a), jnp.asarray(0.3, DTYPE)),
        "slerp(p, Q, T)": (lambda a: jq.slerp(a, q, t), one_q),
    }
    broadcast = re.compile(rf"broadcast_in_dim %arg0,[^\n]*-> tensor<{n}x")
    for name, (call, one) in calls.items():
        assert not broadcast.search(jax.jit(call).lower(one).as_text()), name  # lowered, not compiled
        _assert_as_if_repeated(name, call, one, n)


def test_an_argument_without_batch_axes_is_broadcast_inside_a_row_kernel_s_program():
    """``multiply``, ``plus``, ``minus``, ``from_axis_angle``, the kinematics' rate relations, the
    generalised forces and ``inertia_rate`` form their results from rows of one shape: an argument
    without batch axes is broadcast inside their compiled program, where XLA fuses the broadcast,
    not before it as an eager operation that wrote it to memory at the batch's size (10^6 rows,
    float32, one core, eager: ``plus(Q, delta)`` 4.5-4.7 -> 1.0-1.1 ms, ``minus(Q, q)`` 12.2 ->
    8.5-8.7 ms). An eager call lowers the function's program only (a batch of 11, a shape no
    other test uses); the values are those of the argument repeated for every row, and its
    gradient the sum of theirs."""
    n = 11
    q = jq.random(jax.random.PRNGKey(6), (n,), DTYPE)
    d = jnp.asarray(RNG.normal(size=(n, 3)), DTYPE) * 0.3
    one_q, one_d = jq.random(jax.random.PRNGKey(7), (), DTYPE), d[0]
    angles = jnp.linspace(0.1, 3.0, n, dtype=DTYPE)
    calls = {
        "multiply(Q, q)": (lambda a: jq.multiply(q, a), one_q),
        "multiply(q, Q)": (lambda a: jq.multiply(a, q), one_q),
        "plus(Q, delta)": (lambda a: jq.plus(q, a), one_d),
        "minus(Q, q)": (lambda a: jq.minus(q, a), one_q),
        "qdot_from_omega(Q, w)": (lambda a: jq.qdot_from_omega(q, a), one_d),
        "from_axis_angle(axis, T)": (lambda a: jq.from_axis_angle(a, angles), one_d / jnp.linalg.norm(one_d)),
    }
    for name, (call, one) in calls.items():
        with lowered_programs() as names:
            call(one)
        assert not any("broadcast" in str(x) for x in names), (name, names)
        _assert_as_if_repeated(name, call, one, n)


def _assert_as_if_repeated(name, call, one, n):
    """``call(one)`` and its gradient in ``one`` are those of ``one`` repeated for each of ``n`` rows
    (the same function, row by row), the gradient summed over the rows."""
    tol = 1e-12 if X64 else 2e-5
    both = jax.jit(lambda a: (call(a), jax.grad(lambda b: jnp.sum(jnp.sin(call(b))))(a)))
    value, grad = both(one)
    rows_value, rows_grad = both(jnp.broadcast_to(one, (n,) + one.shape))
    assert_close(value, rows_value, tol=tol, what=name)
    assert_close(grad, rows_grad.sum(axis=0), tol=10 * tol, what=f"{name} gradient")


@pytest.mark.skipif(X64, reason="half precision does not depend on the x64 flag: checked once, in the float32 pass")
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
@pytest.mark.parametrize("name", NAMES)
def test_low_precision_runs(name, dtype):
    fn, args, _ = _make(name, SMOOTH_Q)
    out = fn(*[on_device(a, dtype) for a in args])
    for o in _leaves(out):
        assert o.dtype == dtype, f"{name}: {o.dtype} != {dtype}"
        assert np.all(np.isfinite(np.asarray(o, np.float32)))
    ref = fn(*[on_device(a, np.float32) for a in args])
    for o, r in zip(_leaves(out), _leaves(ref)):
        o, r = np.asarray(o, np.float32), np.asarray(r, np.float32)
        if name.startswith("to_euler"):  # angles near +-pi may wrap either way
            o = r + (o - r + np.pi) % (2 * np.pi) - np.pi
        if name in UNIT_QUAT_OUTPUTS:  # a half turn (|w| within the tolerance of 0): either sign is canonical
            near = (np.abs(r[..., :1]) < 0.1) & (
                np.abs(o + r).max(-1, keepdims=True) < np.abs(o - r).max(-1, keepdims=True)
            )
            o = np.where(near, -o, o)
        # 3 significant digits of float16/bfloat16, amplified a little by the op:
        # 0.1 absolute for O(1) outputs, relative to the output's size beyond that.
        assert_close(o, r, tol=0.1 * max(1.0, float(np.abs(r).max())), what=f"{name} {dtype}")


@functools.cache
def _jacobians(name):
    """One jitted function per registry entry: the outputs and, per output leaf, the reverse- and
    forward-mode Jacobians in the differentiated argument. The smooth-point and singular-point
    tests call it with arguments of the same shapes, so each entry compiles once per run (the
    two tests compiled their own: 52 s + 49 s of float64 test time, nearly all compilation)."""
    fn, _, diff = REGISTRY[name]

    def jacobians(args):
        def leaf(i):
            return lambda y: _leaves(fn(*args[:diff], y, *args[diff + 1 :]))[i]

        n = len(_leaves(fn(*args)))
        x = args[diff]
        return (
            _leaves(fn(*args)),
            [jax.jacrev(leaf(i))(x) for i in range(n)],
            [jax.jacfwd(leaf(i))(x) for i in range(n)],
        )

    return jax.jit(jacobians)


@pytest.mark.skipif(
    not X64,
    reason="central differences need float64; float32 gradients are checked "
    "finite and forward == reverse in test_gradients_finite_at_singular_points",
)
@pytest.mark.parametrize("name", NAMES)
def test_gradients_match_finite_differences(name):
    """Reverse mode, forward mode and central differences agree at smooth points: the gradient
    of a random weighting of the outputs, from the reverse-mode Jacobian, against its forward-mode
    directional derivative and against central differences of the weighted outputs."""
    fn, args, diff = _make(name, SMOOTH_Q)
    args = tuple(jnp.asarray(a, DTYPE) for a in args)
    jacobians = _jacobians(name)
    out, jac_rev, jac_fwd = jax.tree.map(np.asarray, jacobians(args))
    # The contractions in NumPy (float64, as DTYPE in this pass): as eager JAX operations they
    # compiled a program per shape, about 150 small ones over the registry.
    weights = [np.random.default_rng(7).normal(size=o.shape) for o in out]
    x = args[diff]
    direction = np.random.default_rng(8).normal(size=x.shape)
    g_rev = sum(np.tensordot(w, j, axes=w.ndim) for w, j in zip(weights, jac_rev))
    g_fwd = sum(np.sum(w * np.tensordot(j, direction, axes=direction.ndim)) for w, j in zip(weights, jac_fwd))
    assert np.all(np.isfinite(g_rev))
    scale = float(np.abs(g_rev).max()) + 1.0
    assert abs(float(g_fwd) - float(np.sum(g_rev * direction))) <= 1e-10 * scale * x.size

    def loss(y):  # the weighted outputs, from the values the Jacobians' program returns
        a = list(args)
        a[diff] = y
        return sum(np.sum(np.asarray(o) * w) for o, w in zip(jacobians(tuple(a))[0], weights))

    # The points' values come from the compiled Jacobians: a loss program of its own for every
    # entry took 8.7 s of compiling and lowering in the float64 pass; the 80 entries on one core
    # 41.0-41.1 -> 37.5-37.8 s, the Jacobians' evaluations at the points costing the rest
    # (session 56).
    fd = central_difference_jacobian(loss, np.asarray(x), h=1e-6)
    keep = np.setdiff1d(np.arange(len(x)), FD_EXCLUDED_ROWS.get(name, []))
    assert_close(
        np.asarray(g_rev)[keep] / scale, fd[keep] / scale, tol=1e-6, what=f"{name} grad vs central differences"
    )


@pytest.mark.parametrize("name", NAMES)
def test_gradients_finite_at_singular_points(name):
    fn, args, diff = _make(name, SINGULAR_Q)
    out, jac_rev, jac_fwd = _jacobians(name)(tuple(jnp.asarray(a, DTYPE) for a in args))
    for o in out:
        assert np.all(np.isfinite(np.asarray(o))), f"{name} value not finite at a singular point"
    for r, f in zip(jac_rev, jac_fwd):
        assert np.all(np.isfinite(np.asarray(r))), f"{name}: reverse-mode Jacobian not finite at a singular point"
        assert np.all(np.isfinite(np.asarray(f))), f"{name}: forward-mode Jacobian not finite at a singular point"
        assert_close(r, f, tol=1e-9 if X64 else 1e-3, what=f"{name} jacrev vs jacfwd")


# ------------------------------------------------------------------ bad input

BAD_SHAPES = {
    "multiply": lambda: jq.multiply(jnp.zeros((5, 3)), jnp.zeros((5, 4))),
    "conjugate": lambda: jq.conjugate(jnp.zeros((3, 4, 3))),
    "inverse": lambda: jq.inverse(jnp.zeros(3)),
    "norm": lambda: jq.norm(jnp.zeros((2, 5))),
    "normalize": lambda: jq.normalize(jnp.zeros((2, 3))),
    "exp": lambda: jq.exp(jnp.zeros(3)),
    "log": lambda: jq.log(jnp.zeros((4, 3))),
    "power": lambda: jq.power(jnp.zeros(3), 0.5),
    "left_matrix": lambda: jq.left_matrix(jnp.zeros(3)),
    "right_matrix": lambda: jq.right_matrix(jnp.zeros(5)),
    "rotate": lambda: jq.rotate(jnp.zeros(4).at[0].set(1), jnp.zeros(4)),
    "canonicalize": lambda: jq.canonicalize(jnp.zeros(2)),
    "to_matrix": lambda: jq.to_matrix(jnp.zeros((3, 3))),
    "from_matrix": lambda: jq.from_matrix(jnp.zeros((3, 4))),
    "to_rotvec": lambda: jq.to_rotvec(jnp.zeros(3)),
    "from_rotvec": lambda: jq.from_rotvec(jnp.zeros(4)),
    "to_axis_angle": lambda: jq.to_axis_angle(jnp.zeros(3)),
    "from_axis_angle": lambda: jq.from_axis_angle(jnp.zeros(4), 1.0),
    "to_mrp": lambda: jq.to_mrp(jnp.zeros(3)),
    "from_mrp": lambda: jq.from_mrp(jnp.zeros(4)),
    "to_euler": lambda: jq.to_euler(jnp.zeros(3), "xyz"),
    "from_euler": lambda: jq.from_euler(jnp.zeros(4), "xyz"),
    "angle": lambda: jq.angle(jnp.zeros(3)),
    "angle_between": lambda: jq.angle_between(jnp.zeros(4), jnp.zeros(3)),
    "slerp": lambda: jq.slerp(jnp.zeros(4), jnp.zeros(3), 0.5),
    "mean": lambda: jq.mean(jnp.zeros((5, 3))),
    "mean_flat": lambda: jq.mean(jnp.zeros(4)),
    "mean_weights": lambda: jq.mean(jnp.zeros((5, 4)), jnp.ones(4)),
    "align_vectors": lambda: jq.align_vectors(jnp.zeros((5, 3)), jnp.zeros((4, 3))),
    "align_vectors_shape": lambda: jq.align_vectors(jnp.zeros((5, 4)), jnp.zeros((5, 4))),
    "broadcast": lambda: jq.multiply(jnp.zeros((5, 4)), jnp.zeros((3, 4))),
    "slerp_t": lambda: jq.slerp(jnp.zeros((5, 4)), jnp.zeros((5, 4)), jnp.zeros(3)),
    "hat": lambda: jq.hat(jnp.zeros(4)),
    "vee": lambda: jq.vee(jnp.zeros((3, 4))),
    "rate_matrix": lambda: jq.rate_matrix(jnp.zeros(3)),
    "qdot_from_omega": lambda: jq.qdot_from_omega(jnp.zeros(4), jnp.zeros(4)),
    "omega_from_qdot": lambda: jq.omega_from_qdot(jnp.zeros(4), jnp.zeros(3)),
    "qddot_from_alpha": lambda: jq.qddot_from_alpha(jnp.zeros(4), jnp.zeros(4), jnp.zeros(4)),
    "alpha_from_qddot": lambda: jq.alpha_from_qddot(jnp.zeros(4), jnp.zeros(4), jnp.zeros(3)),
    "omega_batch": lambda: jq.qdot_from_omega(jnp.zeros((5, 4)), jnp.zeros((2, 3))),
    "matrix_rate": lambda: jq.matrix_rate(jnp.zeros(4), jnp.zeros(2)),
    "matrix_acceleration": lambda: jq.matrix_acceleration(jnp.zeros(4), jnp.zeros(3), jnp.zeros(4)),
    "point_velocity": lambda: jq.point_velocity(jnp.zeros(4), jnp.zeros(3), jnp.zeros(4)),
    "point_acceleration": lambda: jq.point_acceleration(
        jnp.zeros(4), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), r_ddot=jnp.zeros(2)
    ),
    "inertia_from_points": lambda: jq.inertia_from_points(jnp.zeros(3), jnp.zeros(1)),
    "rotate_inertia": lambda: jq.rotate_inertia(jnp.zeros(4), jnp.zeros(3)),
    "inertia_rate": lambda: jq.inertia_rate(jnp.eye(3), jnp.zeros(4)),
    "quaternion_inertia": lambda: jq.quaternion_inertia(jnp.zeros((4, 4))),
    "angular_momentum": lambda: jq.angular_momentum(jnp.zeros(4), jnp.zeros(3), jnp.eye(4)),
    "kinetic_energy": lambda: jq.kinetic_energy(jnp.zeros(4), jnp.zeros(4), jnp.eye(3)),
    "angular_acceleration": lambda: jq.angular_acceleration(jnp.zeros(4), jnp.zeros(3), jnp.eye(3), jnp.zeros(4)),
    "inverse_dynamics": lambda: jq.inverse_dynamics(jnp.zeros(4), jnp.zeros(3), jnp.zeros(2), jnp.eye(3)),
    "euler_parameter_acceleration": lambda: jq.euler_parameter_acceleration(
        jnp.zeros(4), jnp.zeros(3), jnp.eye(3), jnp.zeros(3)
    ),
    "euler_parameter_acceleration_inertia": lambda: jq.euler_parameter_acceleration(
        jnp.zeros(4), jnp.zeros(4), jnp.ones(3), jnp.zeros(3)
    ),
    "euler_parameter_torque": lambda: jq.euler_parameter_torque(jnp.zeros(4), jnp.zeros(4), jnp.zeros(3), jnp.eye(3)),
    "euler_parameter_mass_matrix": lambda: jq.euler_parameter_mass_matrix(jnp.zeros(3), jnp.eye(3)),
    "euler_parameter_augmented_system": lambda: jq.euler_parameter_augmented_system(
        jnp.zeros(4), jnp.zeros(4), jnp.eye(3), jnp.zeros(4)
    ),
    "norm_constraint_multiplier": lambda: jq.norm_constraint_multiplier(jnp.zeros(4), jnp.zeros(3), jnp.eye(3)),
    "generalized_force": lambda: jq.generalized_force(jnp.zeros(4), jnp.zeros(4)),
    "torque_from_generalized_force": lambda: jq.torque_from_generalized_force(jnp.zeros(4), jnp.zeros(3)),
    "gravity_gradient_torque": lambda: jq.gravity_gradient_torque(jnp.zeros(4), jnp.zeros(4), jnp.eye(3)),
    "dynamics_batch": lambda: jq.kinetic_energy(jnp.zeros((5, 4)), jnp.zeros((5, 3)), jnp.ones((2, 3, 3))),
    "plus": lambda: jq.plus(jnp.zeros(4), jnp.zeros(4)),
    "minus": lambda: jq.minus(jnp.zeros(4), jnp.zeros(3)),
    "right_jacobian": lambda: jq.right_jacobian(jnp.zeros(4)),
    "right_jacobian_inverse": lambda: jq.right_jacobian_inverse(jnp.zeros((2, 2))),
    "left_jacobian": lambda: jq.left_jacobian(jnp.zeros(2)),
    "left_jacobian_inverse": lambda: jq.left_jacobian_inverse(jnp.zeros(4)),
    "adjoint": lambda: jq.adjoint(jnp.zeros(3)),
    "tangent_gradient": lambda: jq.tangent_gradient(jnp.zeros(4), jnp.zeros(3)),
    "squad_segment": lambda: jq.squad_segment(jnp.zeros(4), jnp.zeros(4), jnp.zeros(3), jnp.zeros(4), 0.5),
    "squad_control_points": lambda: jq.squad_control_points(jnp.zeros((5, 3))),
    "squad": lambda: jq.squad(jnp.zeros((5, 3)), 0.5),
    "spline": lambda: jq.RotationSpline(jnp.arange(3.0), jnp.zeros((3, 3))),
}


@pytest.mark.parametrize("case", sorted(BAD_SHAPES))
def test_bad_shape_raises_clear_error(case):
    with pytest.raises(ValueError, match=r"argument|arguments|batch shapes") as err:
        jax.jit(BAD_SHAPES[case])()  # raised while tracing, before anything runs
    msg = str(err.value)
    assert "(..., " in msg or "do not broadcast" in msg, msg


def test_shape_error_names_the_argument_and_expected_shape():
    with pytest.raises(
        ValueError, match=r"argument 'v' must be a 3-vector array shaped \(\.\.\., 3\), got shape \(7, 4\)"
    ):
        jq.rotate(jnp.zeros((7, 4)), jnp.zeros((7, 4)))
    with pytest.raises(
        ValueError, match=r"argument 'm' must be a matrix array shaped \(\.\.\., 3, 3\), got shape \(3, 4\)"
    ):
        jq.from_matrix(jnp.zeros((3, 4)))


@pytest.mark.parametrize("name", ["multiply", "to_matrix", "to_rotvec", "slerp", "to_euler", "rotate", "normalize"])
def test_integer_input_raises_type_error(name):
    qi = jnp.asarray([[1, 0, 0, 0]], jnp.int32)
    call = {
        "multiply": lambda: jq.multiply(qi, qi),
        "to_matrix": lambda: jq.to_matrix(qi),
        "to_rotvec": lambda: jq.to_rotvec(qi),
        "slerp": lambda: jq.slerp(qi, qi, 0.5),
        "to_euler": lambda: jq.to_euler(qi, "xyz"),
        "rotate": lambda: jq.rotate(jnp.asarray([1.0, 0, 0, 0]), jnp.asarray([1, 2, 3])),
        "normalize": lambda: jq.normalize(qi),
    }[name]
    with pytest.raises(TypeError, match="floating dtype"):
        call()


def test_python_lists_are_accepted():
    assert_close(jq.to_matrix([1, 0, 0, 0]), np.eye(3), tol=0)
    assert_close(jq.rotate([0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), [0.0, -1.0, 0.0], tol=1e-6)


def test_python_lists_take_the_dtype_of_the_arrays_they_meet():
    """A list is weakly typed, as a Python scalar is: beside a float32 array the result is
    float32 (it was float64 whenever x64 was on); alone it is JAX's default float."""
    q32 = jnp.asarray([0.6, 0.8, 0.0, 0.0], jnp.float32)
    assert jq.rotate(q32, [1.0, 0.0, 0.0]).dtype == jnp.float32
    assert jq.multiply([1.0, 0.0, 0.0, 0.0], q32).dtype == jnp.float32
    assert jq.slerp(q32, [0.0, 1.0, 0.0, 0.0], 0.5).dtype == jnp.float32
    assert jq.rotate(q32.astype(jnp.float16), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).dtype == jnp.float16
    assert jq.to_matrix([1, 0, 0, 0]).dtype == jnp.asarray(0.0).dtype
    assert_close(jq.rotate(q32, [0.0, 1.0, 0.0]), [0.0, -0.28, 0.96], tol=1e-6)


@pytest.mark.parametrize("exponent", [-30, -25, 20, 30] + ([-300, 300] if X64 else []))
def test_scale_invariant_functions_at_extreme_scales(exponent):
    """90 degrees about x at scale 10^exponent: the squares of the components under- or
    overflow, but the functions documented as scale-invariant scale by a power of two first
    (in float32 angle gave 0 at 1e-25 and to_rotvec gave 0 at 1e20)."""
    q = jnp.asarray([1.0, 1.0, 0.0, 0.0], DTYPE) * jnp.asarray(10.0**exponent, DTYPE)
    tol = 1e-12 if X64 else 1e-6
    half_pi = np.pi / 2
    assert_close(jq.angle(q), half_pi, tol=tol, what="angle")
    assert_close(jq.to_rotvec(q), [half_pi, 0.0, 0.0], tol=tol, what="to_rotvec")
    axis, angle = jq.to_axis_angle(q)
    assert_close(axis, [1.0, 0.0, 0.0], tol=tol, what="axis")
    assert_close(angle, half_pi, tol=tol, what="to_axis_angle")
    assert_close(jq.to_mrp(q), [np.tan(np.pi / 8), 0.0, 0.0], tol=tol, what="to_mrp")
    assert_close(jq.to_euler(q, "xyz"), [half_pi, 0.0, 0.0], tol=tol, what="to_euler")
    assert_close(
        jq.minus(q, jnp.asarray([1.0, 0.0, 0.0, 0.0], DTYPE) * q[0]), [half_pi, 0.0, 0.0], tol=tol, what="minus"
    )


def test_every_public_name_is_in_the_contract():
    # identity/random: tests/test_algebra.py, test_geometry.py; the inertia checks:
    # tests/test_inertia.py (they return booleans / raise); the torque factories:
    # tests/test_torques.py (they return functions).
    # squad and RotationSpline take a whole key sequence (not a batch of rows): their
    # jit/vmap/gradient tests are in tests/test_spline.py; the optimiser helpers in test_lie.py.
    elsewhere = {
        "to_euler",
        "from_euler",
        "identity",
        "random",
        "is_valid_inertia",
        "check_inertia",
        "as_body_torque",
        "circular_orbit_gravity_gradient",
        "squad",
        "RotationSpline",
        "tangent_optimizer",
        "apply_tangent_updates",
        "tangent_gradients",
        # the ODE layer (vector fields, diffrax solvers, simulate): tests/test_integrators.py
        "RigidBody",
        "EulerParameterBody",
        "invariants",
        "LieEuler",
        "RKMK4",
        "RKMK45",
        "RigidBodySplit",
        "RigidBodySplit4",
        "SlerpInterpolation",
        "Simulation",
        "cpu_compiler_options",  # returns options, not arrays: tests/test_threads.py
        "simulate",
        "AbstractSplitting",
        # the Lie solvers on any model and the fixed-step driver: tests/test_lie_solvers.py
        "AbstractLieSolver",
        "AbstractRKMK",
        "RKMKTsit5",
        "RKMK8",
        "BodyRateTerm",
        "solve_fixed_steps",
        "LocalPolynomialInterpolation",
        "AbstractLeafInterpolation",
        # vehicle models with quaternion leaves: tests/test_models.py
        "Quadrotor",
        "ReactionWheelSpacecraft",
        # elliptic functions and the exact torque-free propagator: tests/test_elliptic.py,
        # tests/test_torque_free.py (scalar/principal-moment arguments, own contract tests)
        "ellipj",
        "ellipk",
        "elliprf",
        "elliprj",
        "euler_poinsot",
        "principal_axes",
        "polhode_period",
        "EulerPoinsotSplit",
        "EulerPoinsotSplit4",
        # an eager optimiser (not a traced function): tests/test_time_optimal.py
        "minimum_time_reorientation",
        "Reorientation",
        # the multiple-shooting interior-point layer (NLP solvers): tests/test_optimal_control.py
        "solve_shooting",
        "ShootingProblem",
        "ShootingSolution",
        "ConstrainedReorientation",
        "ReactionWheels",
        "constrained_minimum_time",
        "minimum_energy_reorientation",
        "minimum_fuel_reorientation",
        "optimal_reorientation",
        "refine_mesh",
        "ControlledModel",
        # NumPy functions of a result (the mesh between solves): tests/test_time_optimal.py
        "switch_times",
        "align_mesh",
        # the MEKF (a filter over a time axis, with its own jit/vmap/grad tests): tests/test_mekf.py
        "FilterState",
        "FilterUpdate",
        "FilterResult",
        "mekf_init",
        "mekf_predict",
        "mekf_update",
        "mekf_update_quaternion",
        "mekf",
        "ukf_predict",
        "ukf_update",
        "ukf_update_quaternion",
        "ukf",
    }
    suffixes = ("_nearest", "_body", "_space", "_inertia", "_t")
    covered = set(REGISTRY) | {n[: -len(s)] for n in REGISTRY for s in suffixes if n.endswith(s)}
    assert set(jq.__all__) <= covered | elsewhere, set(jq.__all__) - covered - elsewhere


# ------------------------------------------------------------------ NaN and complex input

# Arguments a function does not read (a body-frame result does not depend on the attitude):
# a NaN there rightly leaves the output finite.
UNUSED_ARGS = {("kinetic_energy", 0), ("angular_acceleration_inertia", 0), ("inverse_dynamics", 0)}


@pytest.mark.parametrize("name", NAMES)
def test_nan_in_gives_nan_out_for_that_element_only(name):
    """A NaN in one element of any argument comes out as NaN in that element's result (never a
    plausible finite value, as the NaN-safe idiom once produced) and leaves the other elements
    alone; or, for inertia tensors checked eagerly, raises an error naming the argument."""
    fn, args, _ = _make(name, SMOOTH_Q)
    for i in range(len(args)):
        bad = [np.array(a, np.float64) for a in args]
        bad[i][3] = np.nan  # every entry of element 3 of argument i
        try:
            out = fn(*[jnp.asarray(a, DTYPE) for a in bad])
        except ValueError as err:
            assert "argument" in str(err), f"{name}: NaN in argument {i} raised an unclear error: {err}"
            continue
        leaves = [np.asarray(o) for o in _leaves(out)]
        for o in leaves:
            assert not np.isnan(np.delete(o, 3, axis=0)).any(), f"{name}: NaN in argument {i} leaked to other elements"
        if (name, i) not in UNUSED_ARGS:
            assert any(np.isnan(o[3]).any() for o in leaves), f"{name}: NaN in argument {i} gave a finite result"


@pytest.mark.parametrize("name", NAMES)
def test_complex_input_raises_type_error(name):
    """Complex arrays and Python lists of complex numbers are rejected like integers (they would
    silently lose their imaginary part)."""
    fn, args, _ = _make(name, SMOOTH_Q[:1])
    for i in range(len(args)):
        as_array = [jnp.asarray(a, DTYPE) for a in args]
        as_array[i] = jnp.asarray(args[i]).astype(jnp.complex64)
        with pytest.raises(TypeError, match="floating dtype"):
            fn(*as_array)
        as_list = [jnp.asarray(a, DTYPE) for a in args]
        as_list[i] = (np.asarray(args[i]) + 1j).tolist()
        with pytest.raises(TypeError, match="floating dtype"):
            fn(*as_list)


def test_lists_of_booleans_are_rejected_and_integer_lists_accepted():
    with pytest.raises(TypeError, match="'q' must have a floating dtype"):
        jq.normalize([True, False, False, False])
    assert_close(jq.normalize([2, 0, 0, 0]), [1.0, 0.0, 0.0, 0.0], tol=0)


# -- The annotations are true ------------------------------------------------------------------
# Every public function's jaxtyping annotations (``Float[ArrayLike, "*#batch 4"]`` for arguments
# whose batch axes broadcast, ``Float[Array, "*batch 4"]`` for results) are checked at run time
# by jaxtyping with beartype: the parameters, the return, and the shape names shared across one
# call. The public functions are wrapped as ``jaxtyping.jaxtyped(typechecker=beartype)`` would
# decorate them, so the calls below fail if an annotation claims a shape, a batch relation or a
# dtype the function does not keep.


@functools.cache
def _typechecked() -> dict:
    """Every public function of jaxquat -> its checked wrapper (made once per test process)."""
    import inspect

    import beartype
    import jaxtyping

    functions = [getattr(jq, name) for name in jq.__all__ if inspect.isfunction(getattr(jq, name))]
    return {f: jaxtyping.jaxtyped(typechecker=beartype.beartype)(f) for f in functions}


@pytest.fixture
def typechecked(monkeypatch):
    """``jq.<name>`` for every public function replaced by its checked wrapper (the registry's
    lambdas look their function up on ``jq`` when called); returns original -> wrapper."""
    wrappers = _typechecked()
    for f, checked in wrappers.items():
        monkeypatch.setattr(jq, f.__name__, checked)
    return wrappers


# The annotations' shapes and batch relations do not depend on the x64 flag (``Float`` admits
# every floating dtype; that each function keeps its input's dtype is checked in both passes by
# test_jit_vmap_and_nested_batching): checked once, in the float64 pass, where the two tests took
# 26.3 s against 32.3 s in the float32 pass (one run of each pass, two workers, 2-core EPYC).
ONE_PASS = pytest.mark.skipif(not X64, reason="annotations do not depend on the x64 flag: checked in the float64 pass")


@ONE_PASS
@pytest.mark.parametrize("name", NAMES)
def test_annotations_hold_for_nested_and_broadcast_batches(name, typechecked):
    fn, args, _ = _make(name, SMOOTH_Q)
    fn = typechecked.get(fn, fn)
    args = [on_device(a, DTYPE) for a in args]
    fn(*[a.reshape((3, 4) + a.shape[1:]) for a in args])  # a nested batch, all arguments alike
    if len(args) > 1:
        # batch shapes that broadcast, (3, 4) against (4,), the second as a NumPy array
        fn(args[0].reshape((3, 4) + args[0].shape[1:]), *[np.asarray(a[:4]) for a in args[1:]])
        # and the other way round: (4,) against (3, 4)
        fn(args[0][:4], *[a.reshape((3, 4) + a.shape[1:]) for a in args[1:]])


@functools.cache
def _inputs():
    """Arguments of the calls below, in broadcast batch shapes ((3, 1) against (4,) where a
    function takes two batched arguments); made once, in the first test that needs them (so
    the filter state comes from the checked ``mekf_init``), not at collection."""
    from types import SimpleNamespace

    rng = np.random.default_rng(7)
    q = jnp.asarray(_unit(rng.normal(size=(3, 1, 4))), DTYPE)
    w = jnp.asarray(rng.normal(size=(4, 3)), DTYPE)
    return SimpleNamespace(
        q=q,
        w=w,
        moments=jnp.asarray([1.0, 2.0, 3.0], DTYPE),
        inertia=jnp.asarray(random_inertias(3, 4), DTYPE),
        m=jnp.asarray(rng.uniform(0.1, 0.9, (3, 1)), DTYPE),
        u=jnp.asarray(rng.uniform(-2, 2, (4,)), DTYPE),
        x=jnp.asarray(rng.uniform(0.5, 2, (3, 1)), DTYPE),
        state=jq.mekf_init(q, w, jnp.eye(6, dtype=DTYPE) * 1e-2),
        vb=jnp.asarray(rng.normal(size=(4, 2, 3)), DTYPE),
    )


# Calls of the public functions outside the registry, on _inputs().
MORE_CALLS = {
    "ellipj": lambda a: jq.ellipj(a.u, a.m),
    "ellipk": lambda a: jq.ellipk(a.m),
    "elliprf": lambda a: jq.elliprf(a.x, a.u**2 + 0.5, a.x + 1),
    "elliprj": lambda a: jq.elliprj(a.x, a.u**2 + 0.5, a.x + 1, a.x + 2),
    "euler_poinsot": lambda a: jq.euler_poinsot(a.q, a.w, a.moments, a.u),
    "polhode_period": lambda a: jq.polhode_period(a.w, a.moments),
    "invariants": lambda a: jq.invariants(a.q, a.w, a.inertia),
    "is_valid_inertia": lambda a: jq.is_valid_inertia(a.inertia),
    "principal_axes": lambda a: jq.principal_axes(a.inertia),
    "squad": lambda a: jq.squad(a.q[:, 0], a.u * 0.2 + 1.0),
    "identity": lambda a: jq.identity((3, 4), DTYPE),
    "random": lambda a: jq.random(jax.random.PRNGKey(0), (3, 4), DTYPE),
    "mekf_predict": lambda a: jq.mekf_predict(a.state, a.w, 0.1, gyro_noise=1e-3, bias_noise=1e-4),
    "mekf_update": lambda a: jq.mekf_update(a.state, a.vb, a.vb, vector_noise=1e-2),
    "mekf_update_quaternion": lambda a: jq.mekf_update_quaternion(a.state, a.q, noise=1e-2),
    "ukf_predict": lambda a: jq.ukf_predict(a.state, a.w, 0.1, gyro_noise=1e-3, bias_noise=1e-4),
    "ukf_update": lambda a: jq.ukf_update(a.state, a.vb, a.vb, vector_noise=1e-2),
    "ukf_update_quaternion": lambda a: jq.ukf_update_quaternion(a.state, a.q, noise=1e-2),
}


@ONE_PASS
@pytest.mark.parametrize("name", sorted(MORE_CALLS))
def test_annotations_hold_beyond_the_registry(name, typechecked):
    MORE_CALLS[name](_inputs())


def _dot_precisions(jaxpr, found):
    """The ``precision`` of every ``dot_general`` in ``jaxpr`` and the jaxprs inside it."""
    found.extend(eqn.params["precision"] for eqn in jaxpr_equations(jaxpr) if eqn.primitive.name == "dot_general")
    return found


@pytest.mark.skipif(not X64, reason="the traced program does not depend on the dtype: checked in the float64 pass")
def test_every_matrix_product_asks_for_full_precision():
    """On a GPU, JAX's default precision runs float32 matrix products in TF32 (a 10-bit mantissa):
    on an H100 that put ``rotate_inertia``'s Jacobian 1.8e-3 and ``mean`` 5.4e-4 rad off in
    float32. Every ``dot_general`` that the registry's functions and their gradients trace (and
    the filters' steps) must ask for ``HIGHEST``; at the commit before the fix, 26 of the 80
    registry functions had products at the default."""
    traced = {}
    for name in NAMES:
        fn, args, diff = _make(name, SMOOTH_Q)
        args = [jnp.asarray(a, DTYPE) for a in args]
        weights = [jnp.ones(o.shape, o.dtype) for o in _leaves(jax.eval_shape(fn, *args))]
        traced[name] = jax.make_jaxpr(jax.grad(_loss(fn, args, diff, weights)))(args[diff])
    inputs = _inputs()
    for name, call in MORE_CALLS.items():
        traced[name] = jax.make_jaxpr(functools.partial(call, inputs))()
    highest = jax.lax.Precision.HIGHEST
    default = {
        name: sum(p is None or any(x != highest for x in p) for p in _dot_precisions(closed.jaxpr, []))
        for name, closed in traced.items()
    }
    bad = {k: v for k, v in default.items() if v}
    assert not bad, f"products at the default precision (name: count): {bad}"


EAGER_ONE_PROGRAM = {
    "multiply": lambda x: jq.multiply(x["q"], x["p"]),
    "from_matrix": lambda x: jq.from_matrix(x["m"]),
    "from_matrix_nearest": lambda x: jq.from_matrix(x["m"], nearest=True),
    "to_rotvec": lambda x: jq.to_rotvec(x["q"]),
    "from_rotvec": lambda x: jq.from_rotvec(x["v"]),
    "to_euler": lambda x: jq.to_euler(x["q"], "ZXZ"),
    "from_euler": lambda x: jq.from_euler(x["v"], "xyz"),
    "slerp": lambda x: jq.slerp(x["q"], x["p"], x["t"]),
    "exp": lambda x: jq.exp(x["q"]),
    "log": lambda x: jq.log(x["q"]),
    "power": lambda x: jq.power(x["q"], x["t"]),
    "canonicalize": lambda x: jq.canonicalize(x["q"]),
    "angle": lambda x: jq.angle(x["q"]),
    "angle_between": lambda x: jq.angle_between(x["q"], x["p"]),
    "to_axis_angle": lambda x: jq.to_axis_angle(x["q"]),
    "from_axis_angle": lambda x: jq.from_axis_angle(x["v"], x["t"]),
    "to_mrp": lambda x: jq.to_mrp(x["q"]),
    "from_mrp": lambda x: jq.from_mrp(x["v"]),
    "mean": lambda x: jq.mean(x["q"]),
    "mean_weighted": lambda x: jq.mean(x["q"], x["t"]),
    "align_vectors": lambda x: jq.align_vectors(x["v"], x["u"]),
    "triad": lambda x: jq.triad(x["v"], x["u"], x["w"], x["r"]),
    "plus": lambda x: jq.plus(x["q"], x["v"], "space"),
    "minus": lambda x: jq.minus(x["q"], x["p"]),
    "right_jacobian": lambda x: jq.right_jacobian(x["v"]),
    "right_jacobian_inverse": lambda x: jq.right_jacobian_inverse(x["v"]),
    "left_jacobian": lambda x: jq.left_jacobian(x["v"]),
    "left_jacobian_inverse": lambda x: jq.left_jacobian_inverse(x["v"]),
    "qdot_from_omega": lambda x: jq.qdot_from_omega(x["q"], x["v"], "space"),
    "omega_from_qdot": lambda x: jq.omega_from_qdot(x["q"], x["p"]),
    "qddot_from_alpha": lambda x: jq.qddot_from_alpha(x["q"], x["p"], x["v"]),
    "alpha_from_qddot": lambda x: jq.alpha_from_qddot(x["q"], x["p"], x["q"], "space"),
    "angular_momentum": lambda x: jq.angular_momentum(x["q"], x["v"], x["i"], "space"),
    "kinetic_energy": lambda x: jq.kinetic_energy(x["q"], x["v"], x["i"]),
    "angular_acceleration": lambda x: jq.angular_acceleration(x["q"], x["v"], x["i"], x["u"]),
    "angular_acceleration, torque-free": lambda x: jq.angular_acceleration(x["q"], x["v"], x["i"]),
    "inverse_dynamics": lambda x: jq.inverse_dynamics(x["q"], x["v"], x["u"], x["i"]),
    "euler_parameter_acceleration": lambda x: jq.euler_parameter_acceleration(x["q"], x["p"], x["i"], x["u"]),
    "euler_parameter_acceleration, torque-free": lambda x: jq.euler_parameter_acceleration(x["q"], x["p"], x["i"]),
    "euler_parameter_torque": lambda x: jq.euler_parameter_torque(x["q"], x["p"], x["q"], x["i"]),
    "euler_parameter_mass_matrix": lambda x: jq.euler_parameter_mass_matrix(x["q"], x["i"]),
    "euler_parameter_augmented_system": lambda x: jq.euler_parameter_augmented_system(x["q"], x["p"], x["i"], x["u"]),
    "euler_parameter_augmented_system, torque-free": lambda x: jq.euler_parameter_augmented_system(
        x["q"], x["p"], x["i"]
    ),
    "norm_constraint_multiplier": lambda x: jq.norm_constraint_multiplier(x["q"], x["p"], x["i"]),
    "generalized_force": lambda x: jq.generalized_force(x["q"], x["u"], "space"),
    "torque_from_generalized_force": lambda x: jq.torque_from_generalized_force(x["q"], x["p"]),
    "rate_matrix": lambda x: jq.rate_matrix(x["q"], "space"),
    "matrix_rate": lambda x: jq.matrix_rate(x["q"], x["v"]),
    "matrix_acceleration": lambda x: jq.matrix_acceleration(x["q"], x["v"], x["u"], "space"),
    "point_velocity": lambda x: jq.point_velocity(x["q"], x["v"], x["r"], x["u"]),
    "point_velocity, body-fixed": lambda x: jq.point_velocity(x["q"], x["v"], x["r"]),
    "point_acceleration": lambda x: jq.point_acceleration(x["q"], x["v"], x["u"], x["r"], x["w"], x["u"]),
    "point_acceleration, body-fixed": lambda x: jq.point_acceleration(x["q"], x["v"], x["u"], x["r"]),
    "inertia_from_points": lambda x: jq.inertia_from_points(x["m"], x["v"]),
    "rotate_inertia": lambda x: jq.rotate_inertia(x["q"], x["i"]),
    "inertia_rate": lambda x: jq.inertia_rate(x["i"], x["v"]),
    "quaternion_inertia": lambda x: jq.quaternion_inertia(x["i"]),
    "principal_axes": lambda x: jq.principal_axes(x["i"]),
    "gravity_gradient_torque": lambda x: jq.gravity_gradient_torque(x["q"], x["r"], x["i"], x["t"]),
    "gravity_gradient_torque, default mu": lambda x: jq.gravity_gradient_torque(x["q"], x["r"], x["i"]),
    "conjugate": lambda x: jq.conjugate(x["q"]),
    "norm": lambda x: jq.norm(x["p"]),
    "inverse": lambda x: jq.inverse(x["p"]),
    "left_matrix": lambda x: jq.left_matrix(x["q"]),
    "right_matrix": lambda x: jq.right_matrix(x["q"]),
    "rotate": lambda x: jq.rotate(x["q"], x["v"]),
    "rotate, NumPy arguments": lambda x: jq.rotate(np.asarray(x["q"]), np.asarray(x["v"])),
    "to_matrix": lambda x: jq.to_matrix(x["q"]),
    "hat": lambda x: jq.hat(x["v"]),
    "vee": lambda x: jq.vee(x["m"]),
    "adjoint": lambda x: jq.adjoint(x["q"]),
    "polhode_period": lambda x: jq.polhode_period(x["v"], x["d"]),
    "attitude_covariance": lambda x: jq.attitude_covariance(x["m"], x["v"]),
    "invariants": lambda x: jq.invariants(x["q"], x["v"], x["i"]),
    "random": lambda x: jq.random(x["k"], (23,), DTYPE),
}


@pytest.mark.skipif(
    not X64,
    reason="how many programs an eager call lowers does not depend on the x64 flag (the same body, "
    "compiled whole either way): checked in the float64 pass (the float32 pass spent 8.5 s on it, session 41)",
)
@pytest.mark.parametrize("name", sorted(EAGER_ONE_PROGRAM))
def test_an_eager_call_lowers_at_most_one_program(name):
    """Outside ``jit`` a public rotation function (and each function of the kinematics, the
    dynamics, the inertia module and the gravity-gradient torque) runs its body as one compiled
    program (``_arrays.compiled``), not as one compilation per operation (6 to 55 of them before,
    each a notebook user waited for); an omitted optional argument (a torque, a point's relative
    velocity) is formed inside that program. Counted by JAX's lowering events on a batch size (23) that no
    other test uses, the inputs made beforehand; at most one, so a program already compiled
    for this shape in the same worker passes as well."""
    rng = np.random.default_rng(23)
    x = {k: jnp.asarray(_unit(rng.normal(size=(23, 4))), DTYPE) for k in "qp"}
    x |= {k: jnp.asarray(rng.normal(size=(23, 3)), DTYPE) for k in "vuwr"}
    x |= {"m": jnp.asarray(rng.normal(size=(23, 3, 3)), DTYPE), "t": jnp.asarray(rng.uniform(0.1, 0.9, 23), DTYPE)}
    x["i"] = jnp.asarray(random_inertias(23, 23), DTYPE)
    x["d"] = jnp.asarray(rng.uniform(1.0, 1.9, size=(23, 3)), DTYPE)  # principal moments
    x["k"] = jax.random.PRNGKey(23)
    jax.block_until_ready(x)
    with lowered_programs() as lowered:
        jax.block_until_ready(EAGER_ONE_PROGRAM[name](x))
    assert len(lowered) <= 1, f"{name}: {len(lowered)} programs lowered: {lowered}"
