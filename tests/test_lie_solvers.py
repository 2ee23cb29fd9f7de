"""The Lie solvers on a user's model (``quaternions=``): a quadrotor ``{r, v, q, w}`` with thrust
along body z, linear drag and a time-varying torque, against scipy's DOP853 on the raw ODE
(rtol 1e-13): measured orders, unit norm without projection, step control, dense output,
events, both diffrax adjoints against finite differences, vmap, bad input."""

from __future__ import annotations

import functools
import re

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.integrate import solve_ivp

import jaxquat as jq
from helpers import (
    DTYPE,
    X64,
    XLA_CHOOSES_EMITTERS,
    assert_close,
    central_difference_jacobian,
    jaxpr_equations,
    lowered_programs,
)

MASS, GRAVITY, DRAG = 1.2, 9.81, 0.3
INERTIA = np.array([0.02, 0.03, 0.05])
MASK = jq.Quadrotor.quaternions
T_END = 2.0
THRUST = 12.5
KEYS = ("r", "v", "q", "w")


def _torque(t):
    return 0.01 * jnp.stack([jnp.sin(3 * t), jnp.cos(2 * t), 0.5 * jnp.ones_like(t)])


def _control(t, y, thrust):
    """Thrust ``args`` along body z; torque ``0.01 (sin 3t, cos 2t, 0.5)``."""
    return thrust, _torque(t).astype(y["w"].dtype)


def _model(dtype=DTYPE):
    return jq.Quadrotor(MASS, jnp.diag(jnp.asarray(INERTIA, dtype)), _control, drag=DRAG, gravity=GRAVITY)


quadrotor = _model()


def _y0(dtype=DTYPE):
    return {
        "r": jnp.zeros(3, dtype),
        "v": jnp.asarray([1.0, 0.0, 0.5], dtype),
        "q": jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.1], dtype)),
        "w": jnp.asarray([2.0, -1.0, 3.0], dtype),
    }


def _raw_rhs(thrust):
    """The quadrotor's raw 13-dimensional ODE in NumPy float64, written out independently of
    jaxquat (rotation matrix from the quaternion, Euler's equations for a diagonal tensor), so
    scipy's reference is float64 whatever JAX's precision mode."""

    def rhs(t, x):
        v, q, w = x[3:6], x[6:10], x[10:]
        a, b, c, d = q / np.linalg.norm(q)
        ez_inertial = np.array([2 * (b * d + a * c), 2 * (c * d - a * b), a * a - b * b - c * c + d * d])
        accel = thrust / MASS * ez_inertial - np.array([0.0, 0.0, GRAVITY]) - DRAG * v
        torque = 0.01 * np.array([np.sin(3 * t), np.cos(2 * t), 0.5])
        wdot = (torque - np.cross(w, INERTIA * w)) / INERTIA
        qw, qv = q[0], q[1:]
        qdot = 0.5 * np.concatenate([[-qv @ w], qw * w + np.cross(qv, w)])
        return np.concatenate([v, accel, qdot, wdot])

    return rhs


def _flat_y0():
    y0 = _y0(np.float64) if X64 else {k: np.asarray(v, np.float64) for k, v in _y0().items()}
    return np.concatenate([np.asarray(y0[k], np.float64) for k in KEYS])


def _unflat(x):
    return {"r": x[:3], "v": x[3:6], "q": x[6:10] / np.linalg.norm(x[6:10]), "w": x[10:]}


@functools.lru_cache(maxsize=None)
def _reference(t_end=T_END):
    """DOP853 on the raw ODE, rtol = atol = 1e-13."""
    sol = solve_ivp(_raw_rhs(THRUST), (0.0, t_end), _flat_y0(), method="DOP853", rtol=1e-13, atol=1e-13)
    return _unflat(sol.y[:, -1])


def _error(y, ref) -> float:
    pos = max(float(np.abs(np.asarray(y[k]) - ref[k]).max()) for k in ("r", "v", "w"))
    return max(pos, float(jq.angle_between(jnp.asarray(y["q"]), jnp.asarray(ref["q"], y["q"].dtype))))


@functools.lru_cache(maxsize=None)
def _fixed_solve(name):
    """One compiled constant-step solve per solver; ``dt0`` and ``n`` traced."""
    solver = SOLVERS[name][0]

    @jax.jit
    def run(dt0):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(quadrotor),
            solver,
            0.0,
            T_END,
            dt0,
            _y0(),
            args=THRUST,
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=1024,
        ).ys

    return run


SOLVERS = {
    "LieEuler": (jq.LieEuler(quaternions=MASK), 1, (0.004, 0.002)),
    "RKMK4": (jq.RKMK4(quaternions=MASK), 4, (0.04, 0.02)),
    "RKMK45": (jq.RKMK45(quaternions=MASK), 5, (0.05, 0.025)),
    "RKMKTsit5": (jq.RKMKTsit5(quaternions=MASK), 5, (0.05, 0.025)),
    "RKMK8": (jq.RKMK8(quaternions=MASK), 8, (0.2, 0.1)),
}


@pytest.mark.skipif(not X64, reason="convergence orders are measured in float64")
@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_measured_order_on_a_quadrotor(name):
    """Halving the step divides the error by 2^p, measured on the whole state at t = 2 (the
    attitude error as an angle): the slope is within 0.35 of the order, and |q| = 1 to 1e-13
    at every saved state without any projection step."""
    _, order, (dt_a, dt_b) = SOLVERS[name]
    ref = _reference()
    ys_a, ys_b = (jax.tree.map(lambda x: x[-1], _fixed_solve(name)(dt)) for dt in (dt_a, dt_b))
    err_a, err_b = _error(ys_a, ref), _error(ys_b, ref)
    slope = np.log2(err_a / err_b)
    assert abs(slope - order) < 0.35, (name, err_a, err_b, slope)
    assert float(jnp.abs(jq.norm(ys_b["q"]) - 1).max()) < 1e-13


@pytest.mark.parametrize("name", ["RKMK45", "RKMKTsit5"])
def test_step_control_dense_output_and_saveat(name):
    """PIDController through the embedded pair: the error at t1 follows the tolerance; the
    dense output (SaveAt(dense=True)) is unit between steps and matches the saved states."""
    solver = SOLVERS[name][0]
    tol = 1e-9 if X64 else 1e-5
    ts = jnp.linspace(0.0, T_END, 5, dtype=DTYPE)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(quadrotor),
        solver,
        0.0,
        T_END,
        0.01,
        _y0(),
        args=THRUST,
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
        saveat=diffrax.SaveAt(ts=ts, t1=True, dense=True),
        max_steps=4096,
    )
    final = jax.tree.map(lambda x: x[-1], sol.ys)
    assert _error(final, _reference()) < (1e-7 if X64 else 2e-3)
    assert int(sol.stats["num_accepted_steps"]) < 400
    dense = jax.vmap(sol.evaluate)(jnp.linspace(0.0, T_END, 37, dtype=DTYPE))
    assert float(jnp.abs(jq.norm(dense["q"]) - 1).max()) < (1e-12 if X64 else 1e-6)
    # between steps: the quartic through the tableau's midpoint against DOP853 (float64 measured
    # 4.4e-9 for RKMK45, 9.1e-10 for RKMKTsit5; the cubic Hermite gave 1.7e-7; float32 9e-5)
    tq = np.linspace(0.0, T_END, 37)
    ref = solve_ivp(_raw_rhs(THRUST), (0.0, T_END), _flat_y0(), method="DOP853", rtol=1e-13, atol=1e-13, t_eval=tq).y.T
    q_ref = jnp.asarray(ref[:, 6:10] / np.linalg.norm(ref[:, 6:10], axis=1, keepdims=True), DTYPE)
    dense_q = jax.vmap(sol.evaluate)(jnp.asarray(tq, DTYPE))
    assert float(jnp.max(jq.angle_between(dense_q["q"], q_ref))) < (2e-8 if X64 else 1e-3)
    assert float(np.abs(np.asarray(dense_q["r"]) - ref[:, :3]).max()) < (2e-8 if X64 else 1e-3)
    at_ts = jax.vmap(sol.evaluate)(ts)
    assert_close(at_ts["q"], sol.ys["q"][:-1], tol=1e-12 if X64 else 1e-5)
    assert_close(at_ts["r"], sol.ys["r"][:-1], tol=1e-12 if X64 else 1e-5)


def test_terminating_event_finds_the_crossing():
    """The quadrotor with weak thrust sinks; an event stops it when the altitude falls to -0.5 m.
    The root finder's time agrees with scipy's DOP853 event time."""

    def altitude(t, y, args, **kwargs):
        return y["r"][2] + 0.5

    solver = jq.RKMK45(quaternions=MASK)
    tol = 1e-10 if X64 else 1e-6  # the root finder too: float32 cannot meet 1e-10
    event = diffrax.Event(altitude, root_finder=optx.Newton(rtol=tol, atol=tol))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(quadrotor),
        solver,
        0.0,
        5.0,
        0.01,
        _y0(),
        args=6.0,
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
        event=event,
        max_steps=4096,
    )
    hit = lambda t, x: x[2] + 0.5  # noqa: E731
    hit.terminal = True
    ref = solve_ivp(_raw_rhs(6.0), (0.0, 5.0), _flat_y0(), method="DOP853", rtol=1e-12, atol=1e-12, events=hit)
    t_ref = ref.t_events[0][0]
    assert 0.3 < t_ref < 5.0
    assert abs(float(sol.ts[-1]) - t_ref) < (1e-7 if X64 else 1e-3), (float(sol.ts[-1]), t_ref)
    assert abs(float(sol.ys["r"][-1, 2]) + 0.5) < (1e-8 if X64 else 1e-4)


def _loss(adjoint):
    def loss(w0, thrust):
        y0 = dict(_y0(), w=w0)
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(quadrotor),
            jq.RKMK45(quaternions=MASK),
            0.0,
            1.0,
            0.01,
            y0,
            args=thrust,
            stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-11),
            adjoint=adjoint,
            max_steps=4096,
        )
        y = jax.tree.map(lambda x: x[-1], sol.ys)
        return jnp.sum(y["q"] * jnp.asarray([0.1, 0.7, -0.3, 0.2])) + jnp.sum(y["r"] ** 2)

    return loss


@functools.cache
def _loss_values():
    """The loss's values, compiled once for both adjoints' tests (the adjoint changes only the
    gradient; each test compiled the same program)."""
    return jax.jit(_loss(diffrax.RecursiveCheckpointAdjoint()))


@pytest.mark.skipif(not X64, reason="finite differences need float64")
@pytest.mark.parametrize(
    "adjoint",
    [diffrax.RecursiveCheckpointAdjoint(), diffrax.BacksolveAdjoint()],
    ids=["RecursiveCheckpoint", "Backsolve"],
)
def test_gradients_through_both_adjoints_match_finite_differences(adjoint):
    """d loss / d (w0, thrust) against central differences (step 1e-6) to 1e-6 relative; the
    backward solve of BacksolveAdjoint runs the same Lie solver on the augmented state."""
    loss = _loss(adjoint)
    w0, thrust = jnp.asarray([2.0, -1.0, 3.0]), jnp.asarray(THRUST)
    g_w, g_t = jax.jit(jax.grad(loss, argnums=(0, 1)))(w0, thrust)
    f = _loss_values()
    eps = 1e-6
    fd_w = np.array([(f(w0 + eps * e, thrust) - f(w0 - eps * e, thrust)) / (2 * eps) for e in np.eye(3)])
    fd_t = (f(w0, thrust + eps) - f(w0, thrust - eps)) / (2 * eps)
    scale = max(np.abs(fd_w).max(), abs(float(fd_t)))
    assert np.abs(np.asarray(g_w) - fd_w).max() < 1e-6 * scale, (g_w, fd_w)
    assert abs(float(g_t) - float(fd_t)) < 1e-6 * scale, (g_t, fd_t)


def test_vmap_tuple_mask_and_float32_unit_norm():
    """A batch of 8 initial rates under vmap equals the single runs; a tuple state with a tuple
    mask gives the same answer as the dict; |q| stays 1 to rounding over 500 steps."""
    solver = jq.RKMK4(quaternions=MASK)
    rates = jnp.asarray(np.random.default_rng(0).normal(size=(8, 3)), DTYPE)

    def run(w0):
        return diffrax.diffeqsolve(
            diffrax.ODETerm(quadrotor), solver, 0.0, 2.0, 0.004, dict(_y0(), w=w0), args=THRUST, max_steps=600
        ).ys

    batched = jax.jit(jax.vmap(run))(rates)
    one = jax.jit(run)(rates[3])
    assert_close(batched["q"][3], one["q"], tol=1e-12 if X64 else 1e-5)
    assert float(jnp.abs(jq.norm(batched["q"]) - 1).max()) < (1e-13 if X64 else 1e-6)

    def as_tuple(t, y, args):
        d = quadrotor(t, dict(zip(("r", "v", "q", "w"), y)), args)
        return tuple(d[k] for k in ("r", "v", "q", "w"))

    y0 = _y0()
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(as_tuple),
        jq.RKMK4(quaternions=(False, False, True, False)),
        0.0,
        2.0,
        0.004,
        tuple(y0[k] for k in ("r", "v", "q", "w")),
        args=THRUST,
        max_steps=600,
    )
    assert_close(sol.ys[2], jax.jit(run)(y0["w"])["q"], tol=1e-12 if X64 else 1e-5)


def test_the_fixed_step_driver_matches_diffeqsolve_on_a_user_model():
    """solve_fixed_steps (lax.scan, no diffeqsolve) gives diffeqsolve's states at the same steps."""
    solver = jq.RKMK4(quaternions=MASK)
    ts = jnp.linspace(0.0, 1.0, 5, dtype=DTYPE)
    ys = jq.solve_fixed_steps(solver, diffrax.ODETerm(quadrotor), ts, _y0(), THRUST, substeps=25)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(quadrotor),
        solver,
        0.0,
        1.0,
        0.01,
        _y0(),
        args=THRUST,
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=200,
    )
    for k in ("r", "v", "q", "w"):
        assert_close(ys[k], sol.ys[k], tol=1e-11 if X64 else 1e-4, what=k)


def _scan_lengths(jaxpr):
    """The ``length`` of every ``scan`` in ``jaxpr`` and the jaxprs inside it."""
    return [eqn.params["length"] for eqn in jaxpr_equations(jaxpr) if eqn.primitive.name == "scan"]


def test_the_fixed_step_driver_over_one_interval_has_no_scan_of_length_one():
    """Two times (one interval): the steps' scan alone, with no scan of length 1 around it, which
    each transform would trace again (the first Adam step through ``simulate``: 1.9 -> 1.6 s).
    The states equal those of the same steps saved over two intervals."""
    solver = jq.RKMK4(quaternions=MASK)
    one = jq.solve_fixed_steps(
        solver, diffrax.ODETerm(quadrotor), jnp.asarray([0.0, 0.5], DTYPE), _y0(), THRUST, substeps=4
    )
    two = jq.solve_fixed_steps(
        solver, diffrax.ODETerm(quadrotor), jnp.asarray([0.0, 0.25, 0.5], DTYPE), _y0(), THRUST, substeps=2
    )
    for k in ("r", "v", "q", "w"):
        assert one[k].shape[0] == 2
        assert_close(one[k][-1], two[k][-1], tol=1e-13 if X64 else 1e-6, what=k)
    jaxpr = jax.make_jaxpr(
        lambda y: jq.solve_fixed_steps(
            solver, diffrax.ODETerm(quadrotor), jnp.asarray([0.0, 0.5], DTYPE), y, THRUST, substeps=4
        )
    )(_y0())
    lengths = _scan_lengths(jaxpr.jaxpr)  # the steps' 4 (and the RKMK stages' own scan)
    assert 1 not in lengths and 4 in lengths, lengths
    q0, w0 = jnp.asarray([[1.0, 0, 0, 0]], DTYPE), jnp.asarray([[0.1, 1.0, 0.2]], DTYPE)
    inertia = jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE))
    ts = np.asarray([0.0, 1.0], DTYPE)
    jaxpr = jax.make_jaxpr(
        jax.grad(lambda w: jnp.sum(jq.simulate(q0, w, inertia, ts, solver=jq.RKMK4(), dt0=0.1).q[..., -1, :] ** 2))
    )(w0)
    lengths = _scan_lengths(jaxpr.jaxpr)
    assert 1 not in lengths and 10 in lengths, lengths


def test_the_fixed_step_driver_called_eagerly_compiles_once_for_new_arrays_of_the_same_shapes():
    """An eager ``solve_fixed_steps`` is one compiled program whose inputs are the arrays of its
    arguments (the term's inertia among them): a second call with another body and state of the
    same shapes lowers nothing, and its states are those of the driver traced into a caller's
    ``jit`` (to the bit)."""

    def run(inertia, w0):
        term = diffrax.ODETerm(jq.RigidBody(jnp.diag(inertia)))
        ts = jnp.asarray([0.0, 0.1, 0.2], DTYPE)
        return jq.solve_fixed_steps(jq.LieEuler(), term, ts, (jnp.asarray([0.6, 0.0, 0.8, 0.0], DTYPE), w0), substeps=2)

    first, second = (jnp.asarray(INERTIA * k, DTYPE) for k in (1.0, 1.5))
    w0, w1 = (jnp.asarray([0.4, -1.1, 0.7], DTYPE) * k for k in (1.0, 2.0))
    run(first, w0)
    with lowered_programs() as names:
        eager = run(second, w1)
    assert names == [], names
    nested = jax.jit(run)(second, w1)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(nested), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_the_fixed_step_driver_s_checkpoint_choices_give_one_gradient():
    """``checkpoint``: True (each step rematerialised) or a ``jax.checkpoint_policies`` policy
    (the products' results kept, as the float32 held-torque rollout does) change what reverse
    mode stores, not the gradient; anything else is refused naming the argument. (A rigid body
    under ``LieEuler``: each gradient program compiles in about 1 s, the quadrotor's under
    ``RKMK4`` in 2.7 s.)"""
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(INERTIA, DTYPE))))
    ts = jnp.asarray([0.0, 0.1, 0.2], DTYPE)
    q0 = jnp.asarray([0.6, 0.0, 0.8, 0.0], DTYPE)
    weights = jnp.asarray([0.3, -0.2, 0.5, 0.1], DTYPE)

    def loss(w, checkpoint):
        qs, ws = jq.solve_fixed_steps(jq.LieEuler(), term, ts, (q0, w), substeps=2, checkpoint=checkpoint)
        return jnp.sum(qs[-1] * weights) + jnp.sum(ws[-1] ** 2)

    grad = jax.jit(jax.grad(loss), static_argnums=1)
    w0 = jnp.asarray([0.4, -1.1, 0.7], DTYPE)
    every, kept = (grad(w0, c) for c in (True, jax.checkpoint_policies.dots_with_no_batch_dims_saveable))
    assert float(jnp.max(jnp.abs(every))) > 1e-2  # not a vanishing gradient
    assert_close(kept, every, tol=1e-13 if X64 else 1e-5, what="gradient")
    with pytest.raises(TypeError, match="checkpoint"):
        jq.solve_fixed_steps(jq.LieEuler(), term, ts, (q0, w0), checkpoint="all")


def _one_step(layout):
    """One step of ``RKMK45`` (its stages, error estimate and first-same-as-last dense output) and
    of ``LieEuler`` from 5 rigid bodies ``(q (5, 4), w (5, 3))``, in ``layout``, and the dense
    output of each at two fifths of the step; one compiled program."""
    rng = np.random.default_rng(1)
    y0 = (jq.normalize(jnp.asarray(rng.normal(size=(5, 4)), DTYPE)), jnp.asarray(rng.normal(size=(5, 3)), DTYPE))
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(INERTIA, DTYPE))))
    out = []
    for cls in (jq.RKMK45, jq.LieEuler):
        solver = cls(layout=layout)
        state = solver.init(term, 0.0, 0.05, y0, None)
        y1, err, dense, _, _ = solver.step(term, 0.0, 0.05, y0, None, state, False)
        out.append((y1, err, solver.interpolation_cls(t0=0.0, t1=0.05, **dense).evaluate(0.02)))
    return out


def test_both_layouts_are_one_method():
    """``layout="rows"`` (the optimal-control transcription's) and the default ``"components"``:
    the same step, error estimate and dense output to rounding, on a batch."""
    rows, parts = (jax.jit(functools.partial(_one_step, layout))() for layout in ("rows", "components"))
    assert rows[0][1] is not None and rows[1][1] is None  # RKMK45's error estimate, none for LieEuler
    for a, b in zip(jax.tree.leaves(rows), jax.tree.leaves(parts)):
        assert a.shape == b.shape and a.shape[0] == 5
        assert_close(b, a, tol=1e-13 if X64 else 2e-6)


@pytest.mark.skipif(not X64, reason="a compiling test: its verdict does not depend on the dtype")
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="one_loop is a loop on CPU only")
def test_the_rows_step_evaluates_its_exponential_once():
    """A ``layout="rows"`` step computes ``Exp(theta)`` once per body: its compiled program (1000
    torque-free bodies, ``LieEuler``, XLA's default CPU emitters, which the suite otherwise turns
    off) holds one range reduction (``_trig.sincos``' rounding to the nearest multiple of pi/2).
    Without the one loop in ``lie_solvers._exp_rows`` XLA copied the exponential into each
    consumer of the end state: four reductions here, and the rollout's forward pass took 1.6-2.2x as
    long (session 88)."""
    rng = np.random.default_rng(2)
    y0 = (jq.normalize(jnp.asarray(rng.normal(size=(1000, 4)))), jnp.asarray(rng.normal(size=(1000, 3))))
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(INERTIA))))
    solver = jq.LieEuler(layout="rows")
    emitters = {"xla_cpu_use_fusion_emitters": True} if XLA_CHOOSES_EMITTERS else None

    def step(y):
        y1 = solver.step(term, 0.0, 0.05, y, None, None, False)[0]
        return y1, jq.normalize(y1[0])  # the end state's two users, as in a scan's carry and output

    text = jax.jit(step, compiler_options=emitters).lower(y0).compile().as_text()
    assert len(re.findall(r"= \S+ round-nearest-even\(", text)) == 1
    np.testing.assert_allclose(jq.norm(step(y0)[0][0]), 1.0, atol=1e-14)


def _pd_torque(t, q, w, gains):
    """A body torque reading every argument, written for rows ``(..., 4)``, ``(..., 3)``."""
    return -gains[0] * q[..., 1:] - gains[1] * w + 0.05 * jnp.sin(3.0 * t)


def _rigid_bodies():
    """5 bodies, a full shared tensor and one per body, with the torque and its gains."""
    rng = np.random.default_rng(7)
    y0 = (jq.normalize(jnp.asarray(rng.normal(size=(5, 4)), DTYPE)), jnp.asarray(rng.normal(size=(5, 3)), DTYPE))
    turn = jq.to_matrix(jq.normalize(jnp.asarray([0.9, 0.2, -0.3, 0.1], DTYPE)))
    full = turn @ jnp.diag(jnp.asarray([2.0, 3.0, 4.0], DTYPE)) @ turn.T
    per_body = jnp.stack([full * s for s in (1.0, 1.2, 0.8, 1.5, 1.1)])
    return y0, full, per_body, jnp.asarray([0.4, 0.7], DTYPE)


# LieEuler (its own step), RKMK4 (fixed steps) and RKMK45 (error estimate, carried first stage,
# dense output through the midpoint weights); RKMKTsit5 and RKMK8 take RKMK45's path with other
# tableaus (all five took 51 s in float64, these three 13 s)
_SOLVERS = (jq.LieEuler, jq.RKMK4, jq.RKMK45)


@functools.partial(jax.jit, static_argnums=0)
def _init_state(solver, inertia, y0, gains):
    """``solver.init`` on the rigid body of ``inertia`` under the PD torque, over ``[0, 0.05]``."""
    return solver.init(diffrax.ODETerm(jq.RigidBody(inertia, _pd_torque)), 0.0, 0.05, y0, gains)


@functools.partial(jax.jit, static_argnums=0)
def _step_and_dense(solver, inertia, t0, t1, y, gains, state, jump, t):
    """One step of ``solver`` on the rigid body of ``inertia`` under the PD torque (``jump`` a
    traced bool, as diffrax passes ``made_jump``) and its dense output at ``t``: a program of its
    own, so that the steps sharing a solver and a tensor shape share it. In one program (the test
    before session 56) each of RKMK45's three steps on the full tensor was a copy of the step:
    20198 HLO operations, 7.2 s of compiling, against 6739 and 2.2 s for one."""
    y1, err, dense, state1, _ = solver.step(
        diffrax.ODETerm(jq.RigidBody(inertia, _pd_torque)), t0, t1, y, gains, state, jump
    )
    return y1, err, solver.interpolation_cls(t0=t0, t1=t1, **dense).evaluate(t), state1


@functools.partial(jax.jit, static_argnums=0)
def _backwards(layout, y0, full, gains):
    """RKMK45 from 0.3 back to 0 (``diffeqsolve`` wraps the term with the direction)."""
    term = diffrax.ODETerm(jq.RigidBody(full, _pd_torque))
    return diffrax.diffeqsolve(term, jq.RKMK45(layout=layout), 0.3, 0.0, -0.05, y0, args=gains).ys


def _steps_of(layout):
    """For each solver, from ``_rigid_bodies``: one step from ``init`` with a full shared tensor
    and with one per body, then with the shared tensor a second step carrying the first's solver
    state (``made_jump`` False, then True), the dense output of each at 0.4 of the step; and a
    solve backwards in time (``diffeqsolve`` wraps the term with the direction)."""
    y0, full, per_body, gains = _rigid_bodies()
    times = [jnp.asarray(t, DTYPE) for t in (0.0, 0.05, 0.1, 0.02, 0.07)]
    no, yes = jnp.asarray(False), jnp.asarray(True)
    out = []
    for cls in _SOLVERS:
        solver = cls(layout=layout)
        for inertia in (per_body, full):
            state = _init_state(solver, inertia, y0, gains)
            y1, err, at, state = _step_and_dense(solver, inertia, *times[:2], y0, gains, state, no, times[3])
            out.append((y1, err, at, state))
        for jump in (no, yes):
            out.append(_step_and_dense(solver, full, *times[1:3], y1, gains, state, jump, times[4]))
    out.append(_backwards(layout, y0, full, gains))
    return out


def test_a_rigid_body_model_is_stepped_in_components_as_the_generic_step_would():
    """On a model with ``euler_equations()`` (``RigidBody``) the component layout steps the body
    one array per component (``struct_of_arrays.lie_step``); the row layout keeps the generic
    step, which runs the model's field on rows. Every solver, a full tensor and one per body, a
    torque reading ``(t, q, w, args)``: the same steps, error estimates, dense output, carried
    first stages (first-same-as-last) and a solve backwards in time, to rounding."""
    from jaxquat.integration import struct_of_arrays

    calls = []
    original = struct_of_arrays.lie_step

    def spy(*a, **k):
        calls.append(1)
        return original(*a, **k)

    struct_of_arrays.lie_step = spy
    try:
        parts = _steps_of("components")
        assert calls, "the component step was not taken"
        calls.clear()
        rows = _steps_of("rows")
        assert not calls
    finally:
        struct_of_arrays.lie_step = original
    assert jax.tree.structure(rows) == jax.tree.structure(parts)
    for a, b in zip(jax.tree.leaves(rows), jax.tree.leaves(parts)):
        assert_close(b, a, tol=1e-13 if X64 else 1e-5)  # measured 4.4e-16 and 6.0e-7


def test_the_component_step_takes_args_that_are_not_arrays():
    """The component step is a jitted function of its arrays: ``args`` leaves that are not arrays
    (a string, a Python float) reach the torque as they are, and the steps are the row layout's."""

    def torque(t, q, w, a):
        return -a["k"] * w * (2.0 if a["mode"] == "double" else 1.0)

    y0, full, _, _ = _rigid_bodies()
    ys = [
        diffrax.diffeqsolve(
            diffrax.ODETerm(jq.RigidBody(full, torque)),
            jq.RKMK4(layout=layout),
            0.0,
            0.2,
            0.05,
            y0,
            args=dict(k=0.5, mode="double"),
        ).ys
        for layout in ("rows", "components")
    ]
    for a, b in zip(*ys):
        assert_close(b, a, tol=1e-13 if X64 else 1e-5)


def _step_loss(layout, w0, inertia, gains):
    """One ``RKMK45`` step on a ``RigidBody`` from ``init``'s carried first stage, a loss reading
    the state, the error estimate and the dense output."""
    y0, _, _, _ = _rigid_bodies()
    term = diffrax.ODETerm(jq.RigidBody(inertia, _pd_torque))
    solver = jq.RKMK45(layout=layout)
    state = solver.init(term, 0.0, 0.05, (y0[0], w0), gains)
    y, err, dense, _, _ = solver.step(term, 0.0, 0.05, (y0[0], w0), gains, state, False)
    mid = solver.interpolation_cls(t0=0.0, t1=0.05, **dense).evaluate(0.02)
    weights = jnp.arange(4.0, dtype=DTYPE)[None]
    return jnp.sum(y[0] * weights) + jnp.sum(y[1] ** 2) + jnp.sum(err[1] * y[1]) + jnp.sum(mid[0] ** 3)


_step_grads = jax.jit(jax.grad(_step_loss, argnums=(1, 2, 3)), static_argnums=0)


def test_the_component_step_s_gradients_are_the_generic_step_s():
    """Reverse mode through an ``RKMK45`` step on a ``RigidBody`` (state, error estimate, dense
    output, the carried first stage): the gradients with respect to the initial rates, a full
    inertia tensor and the torque's gains in the component step (its inputs, the inertia's
    entries and the step through one backward loop) equal the generic step's
    (``layout="rows"``) to rounding, and are finite. The component step's stages read the
    tensor's symmetric part (``EulerEquations``), the generic step all nine entries, so the two
    gradients with respect to the tensor agree in their symmetric parts (``(G + G^T) / 2``: the
    derivative along every symmetric change). (Through a whole adaptive solve: the next test.)"""
    y0, full, _, gains = _rigid_bodies()
    rows = list(_step_grads("rows", y0[1], full, gains))
    parts = list(_step_grads("components", y0[1], full, gains))
    for g in (rows, parts):
        g[1] = 0.5 * (g[1] + jnp.swapaxes(g[1], -1, -2))
    for a, b in zip(rows, parts):
        assert np.all(np.isfinite(np.asarray(b)))
        assert_close(b, a, tol=1e-11 if X64 else 1e-4)  # measured 4.4e-16 and 4.8e-7 (entries up to 4.9)


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_through_an_adaptive_solve_recomputing_from_checkpoints_match_finite_differences():
    """``jit(grad)`` through ``diffeqsolve`` with ``RKMK45`` (the component step) on a ``RigidBody``
    over 49 steps with 8 checkpoints, so that the backward pass recomputes steps from them (as
    ``simulate``'s default adjoint, 64 checkpoints per body, does past 64 steps): the gradients in
    the initial rates, the full inertia tensor and the gains are central differences' (measured
    8.1e-10, 1.5e-9 and 4.4e-10 relative to the largest entry; the bound 1e-6)."""
    y0, full, _, gains = _rigid_bodies()

    def loss(w0, inertia, k):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.RigidBody(inertia, _pd_torque)),
            jq.RKMK45(),
            0.0,
            3.0,
            0.05,
            (y0[0], w0),
            args=k,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=diffrax.SaveAt(t1=True),
            adjoint=diffrax.RecursiveCheckpointAdjoint(checkpoints=8),
            max_steps=256,
        )
        value = jnp.sum(sol.ys[0][-1] * jnp.arange(4.0, dtype=DTYPE)[None]) + jnp.sum(sol.ys[1][-1] ** 2)
        return value, sol.stats["num_steps"]

    # one compiled program for the gradient, the step count and every finite-difference value
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))
    args = (y0[1], full, gains)
    (_, steps), grads = value_and_grad(*args)
    assert int(steps) > 8, steps
    for i, g in enumerate(grads):

        def partial(x, i=i):
            return value_and_grad(*args[:i], x, *args[i + 1 :])[0][0]

        fd = central_difference_jacobian(partial, np.asarray(args[i]))
        scale = max(1e-3, float(np.abs(fd).max()))
        assert_close(np.asarray(g) / scale, fd / scale, tol=1e-6, what=f"gradient {i}")


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_the_component_step_s_input_cotangents_come_out_of_one_loop():
    """Reverse mode through one ``RKMK45`` step on a ``RigidBody`` (from a carried first stage):
    the cotangents of ``q`` (4), ``w`` (3) and the carried stage's ``(w_s, dw_s/dt)`` (3 + 3) are
    the operands of one variadic ``reduce`` (one loop on CPU). Left out of it, the carried
    stage's cotangents were reductions of their own over the backward step, compiled by XLA's
    fusion emitters into code that took 1.3 s for 10 bodies instead of 0.6 ms."""
    y0, full, _, gains = _rigid_bodies()
    term = diffrax.ODETerm(jq.RigidBody(full, _pd_torque))
    solver = jq.RKMK45()
    state = solver.init(term, 0.0, 0.05, y0, gains)

    def loss(y, carried):
        y1 = solver.step(term, 0.0, 0.05, y, gains, carried, False)[0]
        return jnp.sum(y1[0] ** 3) + jnp.sum(y1[1] ** 3)

    text = jax.export.export(jax.jit(jax.grad(loss, argnums=(0, 1))), platforms=["cpu"])(y0, state).mlir_module()
    assert re.search(r"%\w+:13 = stablehlo\.reduce\(", text)


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_a_step_without_dense_output_computes_only_the_state_in_its_last_loop():
    """``RKMK4`` (no error estimate, no carried stage) on a ``RigidBody`` in ``diffeqsolve``: the
    component step's last loop writes the state's 4 + 3 components and nothing more. Writing the
    increments, the dense output's slopes and the last stage too (31 arrays), a fixed-step
    ``diffeqsolve`` of 1000 bodies took 52 ms against 7.3 ms once the step was a jitted function
    of its own (XLA keeping the unused outputs)."""
    y0, full, _, gains = _rigid_bodies()
    term = diffrax.ODETerm(jq.RigidBody(full, _pd_torque))

    def solve(y):
        return diffrax.diffeqsolve(term, jq.RKMK4(), 0.0, 0.2, 0.05, y, args=gains).ys

    text = jax.jit(solve).lower(y0).as_text()
    sizes = [int(n) for n in re.findall(r"%\w+:(\d+) = stablehlo\.reduce\(", text)]
    assert max(sizes) == 7, sizes


def test_a_step_end_dense_output_gives_the_ends_and_nan_inside():
    """``saves_at_step_ends=True``: the dense output is ``y0`` at ``t0`` and ``y1`` at ``t1``, each
    to 16 units of rounding of the times (one unit short of a saved time is that time), the
    difference form ``y(t1) - y(t0)``, and NaN strictly inside the step."""
    solver = jq.RKMK45(saves_at_step_ends=True)
    y0 = (jq.identity((), DTYPE), jnp.asarray([0.1, 0.2, 0.3], DTYPE))
    y1 = (jq.from_rotvec(jnp.asarray([0.0, 0.0, 0.1], DTYPE)), jnp.asarray([0.4, 0.5, 0.6], DTYPE))
    t0, t1 = jnp.asarray(4.0, DTYPE), jnp.asarray(4.2, DTYPE)
    interp = solver.interpolation_cls(t0=t0, t1=t1, y0=y0, y1=y1)
    below = jnp.nextafter(t1, jnp.asarray(0.0, DTYPE))
    for t, want in ((t0, y0), (t1, y1), (below, y1)):
        for a, b in zip(interp.evaluate(t), want):
            assert_close(a, b, tol=0.0)
    for a, b, c in zip(interp.evaluate(t0, t1), y0, y1):
        assert_close(a, c - b, tol=0.0)
    inside = interp.evaluate(jnp.asarray(4.1, DTYPE))
    assert all(bool(jnp.all(jnp.isnan(x))) for x in inside)


def test_a_solver_saving_at_step_ends_saves_what_the_interpolation_would_there():
    """``diffeqsolve`` with ``RKMK45``, ``SaveAt(ts)`` and ``ClipStepSizeController(step_ts=ts)`` on
    16 bodies: with ``saves_at_step_ends=True`` the saved states equal those of the default dense
    output (which at a step's end is the step's end to rounding), none is NaN (one body ends a
    step one unit of rounding short of ``t = 4.2``, and the next step saves it), and the steps
    are the same."""
    rng = np.random.default_rng(0)
    y0 = (jq.normalize(jnp.asarray(rng.normal(size=(16, 4)), DTYPE)), jnp.asarray(rng.normal(size=(16, 3)), DTYPE))
    ts = jnp.linspace(0.0, 5.0, 26, dtype=DTYPE)
    tol = 1e-9 if X64 else 1e-5

    def torque(t, q, w, k):
        return -k * q[..., 1:] - 0.8 * w + 0.1 * jnp.sin(t)

    @functools.partial(jax.jit, static_argnums=0)
    def solve(ends, y):
        def one(q, w):
            sol = diffrax.diffeqsolve(
                diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE)), torque)),
                jq.RKMK45(saves_at_step_ends=ends),
                ts[0],
                ts[-1],
                None,
                (q, w),
                args=jnp.asarray(0.5, DTYPE),
                saveat=diffrax.SaveAt(ts=ts),
                stepsize_controller=diffrax.ClipStepSizeController(
                    diffrax.PIDController(rtol=tol, atol=tol), step_ts=ts
                ),
            )
            return sol.ys, sol.stats["num_steps"]

        return jax.vmap(one)(*y)

    (ends, n_ends), (dense, n_dense) = solve(True, y0), solve(False, y0)
    assert bool(jnp.all(n_ends == n_dense))
    for a, b in zip(ends, dense):
        assert not bool(jnp.any(jnp.isnan(a)))
        assert_close(a, b, tol=1e-13 if X64 else 1e-5)  # measured 1.6e-15 and 3.6e-7


class _Spy:
    """The quadrotor's field, counting the calls of its body-rate form."""

    calls = 0

    def __call__(self, t, y, args):
        return quadrotor(t, y, args)

    def body_rate_field(self, t, y, args):
        _Spy.calls += 1
        return quadrotor.body_rate_field(t, y, args)


def _there_and_back(field):
    """``RKMK4`` over [0, 0.5] and back to 0 by ``diffeqsolve`` (which wraps the term with the
    time direction), 25 steps each way."""
    term = diffrax.ODETerm(field)
    solver = jq.RKMK4(quaternions=MASK)
    there = diffrax.diffeqsolve(term, solver, 0.0, 0.5, 0.02, _y0(), args=THRUST, max_steps=64).ys
    mid = jax.tree.map(lambda x: x[-1], there)
    back = diffrax.diffeqsolve(term, solver, 0.5, 0.0, -0.02, mid, args=THRUST, max_steps=64).ys
    return mid, jax.tree.map(lambda x: x[-1], back)


def test_a_model_s_body_rate_field_replaces_reading_the_rate_from_qdot():
    """Given a plain ``ODETerm`` of a model with ``body_rate_field`` the solver steps on the model's
    body rates (no ``qdot`` read back), forward and backward in time: the same states, to
    rounding, as the generic path (the same field behind a lambda); and the model's own field is
    its body-rate form with ``q (0, w)/2`` on the attitude."""
    _Spy.calls = 0
    direct = jax.jit(lambda: _there_and_back(_Spy()))()
    assert _Spy.calls > 0
    generic = jax.jit(lambda: _there_and_back(lambda t, y, args: quadrotor(t, y, args)))()
    for a, b in zip(jax.tree.leaves(direct), jax.tree.leaves(generic)):
        assert_close(a, b, tol=1e-13 if X64 else 1e-5)  # measured 7.9e-16 and 9.6e-7 (|w| up to 3)
    assert_close(direct[1]["q"], _y0()["q"], tol=1e-7 if X64 else 1e-4)  # there and back: 4th order, 25 steps
    lie, plain = quadrotor.body_rate_field(0.3, _y0(), THRUST), quadrotor(0.3, _y0(), THRUST)
    assert_close(plain["q"], jq.multiply(_y0()["q"], jnp.concatenate([jnp.zeros(1, DTYPE), lie["q"]])) / 2)
    for k in ("r", "v", "w"):
        assert_close(plain[k], lie[k], tol=0.0, what=k)


def test_a_bad_layout_raises_naming_layout():
    with pytest.raises(ValueError, match="'layout'.*components.*rows"):
        jq.RKMK4(layout="soa")


@pytest.mark.parametrize(
    "mask, error, match",
    [
        ({"r": False, "q": True}, ValueError, "'quaternions'.*prefix"),
        ({"r": False, "v": True, "q": True, "w": False}, ValueError, r"'quaternions'.*\(\.\.\., 4\)"),
        ({"r": False, "v": False, "q": "yes", "w": False}, TypeError, "'quaternions'.*bool"),
    ],
)
def test_bad_masks_raise_naming_quaternions(mask, error, match):
    with pytest.raises(error, match=match):
        diffrax.diffeqsolve(diffrax.ODETerm(quadrotor), jq.RKMK4(quaternions=mask), 0.0, 0.1, 0.01, _y0(), args=THRUST)


def test_without_a_mask_a_non_rigid_body_state_gets_a_clear_error():
    with pytest.raises(TypeError, match="quaternions="):
        diffrax.diffeqsolve(diffrax.ODETerm(quadrotor), jq.RKMK4(), 0.0, 0.1, 0.01, _y0(), args=THRUST)


@pytest.mark.skipif(
    not X64,
    reason="midpoint_weights computes in float64 under either x64 flag, and the weights are constants: "
    "checked in the float64 pass (its eager evaluation compiled 37 small programs in the float32 pass)",
)
@pytest.mark.parametrize(
    "solver, source", [(jq.RKMK45, diffrax.Dopri5), (jq.RKMKTsit5, diffrax.Tsit5), (jq.RKMK8, diffrax.Dopri8)]
)
def test_midpoint_weights_are_those_of_diffrax_s_own_dense_output(solver, source):
    """The literal b_i(1/2) of each adaptive RKMK solver equal diffrax's continuous extension
    of the same tableau at the step's midpoint, bit for bit (computed in float64 always), and
    integrate a constant to the midpoint (sum b_i(1/2) = 1/2: to 1e-14, since Dopri8's
    rational coefficients are rounded and the 14 terms, up to 0.31 each, sum to 1.6e-15 off)."""
    from jaxquat.integration.lie_solvers import midpoint_weights

    np.testing.assert_array_equal(solver.mid_weights, midpoint_weights(source))
    assert solver.mid_weights.dtype == np.float64 and len(solver.mid_weights) == source.tableau.num_stages
    assert abs(solver.mid_weights.sum() - 0.5) < 1e-14
