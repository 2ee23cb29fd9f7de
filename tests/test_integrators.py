"""Rigid-body solvers inside diffrax: against the symmetric top in closed form and a tight
scipy DOP853 reference, unit norm with no renormalisation, momentum conservation of the
splittings, measured convergence orders, gradients through the solve, batching."""

from __future__ import annotations

import functools
import re
import os
import subprocess
import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from frames import script_in_deep_frame
from helpers import (
    DTYPE,
    X64,
    XLA_CHOOSES_EMITTERS,
    ChunkSeen,
    assert_close,
    central_difference_jacobian,
    dop853_reference,
    lowered_programs,
    spy_on_chunk_sizes,
)

I_DIAG = np.array([1.0, 2.0, 3.0])
W0 = np.array([1.0, 0.1, 0.5])
SOLVERS = {
    "LieEuler": (jq.LieEuler(), 1),
    "RKMK4": (jq.RKMK4(), 4),
    "RKMK45": (jq.RKMK45(), 5),
    "RigidBodySplit": (jq.RigidBodySplit(), 2),
    "RigidBodySplit4": (jq.RigidBodySplit4(), 4),
}
SPLITTINGS = {
    "RigidBodySplit": (jq.RigidBodySplit(), 2),
    "RigidBodySplit4": (jq.RigidBodySplit4(), 4),
    "EulerPoinsotSplit": (jq.EulerPoinsotSplit(), 2),
    "EulerPoinsotSplit4": (jq.EulerPoinsotSplit4(), 4),
}


def _dop853(t_end, ts, inertia=I_DIAG, w0=W0):
    return dop853_reference(np.array([1.0, 0, 0, 0]), w0, inertia, ts)


def _symmetric_top(ts, it, i3, w0):
    """Closed form: q(t) = Exp(|H| t / It h_s) q0 Exp((1/I3 - 1/It) m3 t e3), q0 = identity."""
    m = np.array([it * w0[0], it * w0[1], i3 * w0[2]])
    h = np.linalg.norm(m)
    outer = np.outer(ts * h / it, m / h)
    inner = np.outer(ts * (1 / i3 - 1 / it) * m[2], [0.0, 0.0, 1.0])
    return jq.multiply(jq.from_rotvec(jnp.asarray(outer)), jq.from_rotvec(jnp.asarray(inner)))


@pytest.mark.skipif(not X64, reason="accuracy bars are float64 figures")
@pytest.mark.parametrize(
    "name,dt,bound", [("RKMK45", None, 1e-7), ("RKMK4", 0.01, 1e-8), ("RigidBodySplit4", 0.01, 5e-7)]
)
def test_symmetric_top_closed_form(name, dt, bound):
    it, i3, w0 = 2.0, 3.5, np.array([0.4, -0.3, 1.3])
    ts = np.linspace(0.0, 50.0, 11)
    sim = jq.simulate(
        jq.identity(),
        jnp.asarray(w0),
        jnp.diag(jnp.asarray([it, it, i3])),
        jnp.asarray(ts),
        solver=SOLVERS[name][0],
        dt0=dt,
        rtol=1e-11,
        atol=1e-11,
    )
    err = np.asarray(jq.angle_between(sim.q, _symmetric_top(ts, it, i3, w0)))
    assert err.max() < bound, err


@pytest.mark.skipif(not X64, reason="accuracy bars are float64 figures")
def test_asymmetric_top_against_dop853_and_invariants():
    ts = np.linspace(0.0, 100.0, 21)
    q_ref, w_ref = _dop853(100.0, ts)
    for name, dt, bound in (
        ("RKMK45", None, 1e-6),
        ("RKMK4", 0.01, 1e-8),
        ("RigidBodySplit", 0.01, 1e-4),
        ("RigidBodySplit4", 0.01, 1e-7),
    ):
        sim = jq.simulate(
            jq.identity(),
            jnp.asarray(W0),
            jnp.diag(jnp.asarray(I_DIAG)),
            jnp.asarray(ts),
            solver=SOLVERS[name][0],
            dt0=dt,
            rtol=1e-10,
            atol=1e-10,
        )
        err = np.asarray(jq.angle_between(sim.q, jnp.asarray(q_ref)))
        assert err.max() < bound, (name, err.max())
        inv = jq.invariants(sim.q, sim.omega, jnp.diag(jnp.asarray(I_DIAG)))
        assert float(jnp.abs(inv["norm_error"]).max()) < 1e-13, (name, "norm")  # splittings: no renormalisation
        if name.startswith("RigidBodySplit"):
            h = np.asarray(inv["momentum_space"])
            drift = np.abs(h - h[0]).max() / np.linalg.norm(h[0])
            assert drift < 1e-12, (name, drift)  # spatial momentum exact to rounding


@pytest.mark.skipif(not X64, reason="convergence orders are measured in float64")
@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_measured_convergence_order(name):
    solver, order = SOLVERS[name]
    t_end = 2.0
    q_ref, _ = _dop853(t_end, np.array([0.0, t_end]))
    # step pairs in each method's asymptotic range, above the rounding floor (~1e-13)
    dts = {1: (0.004, 0.002), 2: (0.004, 0.002), 4: (0.02, 0.01), 5: (0.2, 0.1)}[order]
    errs = []
    for dt in dts:
        sim = _fixed(solver, dt, t_end)  # RKMK45 too runs at fixed steps here
        errs.append(float(jq.angle_between(sim[-1], jnp.asarray(q_ref[-1]))))
    measured = np.log2(errs[0] / errs[1])
    assert abs(measured - order) < 0.35, (name, errs, measured)


def _fixed(solver, dt, t_end):
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(I_DIAG))))
    sol = diffrax.diffeqsolve(
        term,
        solver,
        0.0,
        t_end,
        dt,
        (jq.identity(), jnp.asarray(W0)),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=10_000,
    )
    return sol.ys[0]


_TARGET = np.asarray([0.3, -0.2, 0.5])
_GRAD_ARGS = (np.asarray([0.4, -0.2, 0.3]), np.asarray([1.0, 2.0, 2.5]), np.asarray(0.7))


def _constant_torque(t, q, w, k):
    return jnp.broadcast_to(k * jnp.asarray([0.1, -0.2, 0.05]), w.shape)


def _final_attitude_loss(**simulate_options):
    """loss(omega0, principal moments, torque gain) on the attitude at t = 1.5."""

    def loss(w0, moments, k):
        sim = jq.simulate(
            jq.identity(),
            w0,
            jnp.diag(moments),
            jnp.asarray([0.0, 1.5]),
            torque=_constant_torque,
            args=k,
            **simulate_options,
        )
        return jnp.sum((sim.q[-1] - jq.from_rotvec(jnp.asarray(_TARGET))) ** 2)

    return loss


def _check_gradients_against_central_differences(loss, what, loss_fn=None):
    """jax.grad in each argument against central differences, 1e-6 relative to the largest entry;
    the differences of ``loss_fn`` (a compiled loss of the same values), by default ``jit(loss)``."""
    args = tuple(jnp.asarray(a) for a in _GRAD_ARGS)
    grad_fn = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))
    loss_fn = jax.jit(loss) if loss_fn is None else loss_fn  # one compilation for every difference
    for i, g in enumerate(grad_fn(*args)):

        def partial(x, i=i):
            a = list(args)
            a[i] = x
            return loss_fn(*a)

        fd = central_difference_jacobian(partial, np.asarray(args[i]), h=1e-6)
        scale = max(1e-3, float(np.abs(fd).max()))
        assert_close(np.asarray(g) / scale, fd / scale, tol=1e-6, what=f"{what} gradient {i}")
    return grad_fn


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_through_the_solve_match_finite_differences():
    """grad of a final-attitude loss w.r.t. omega0, the inertia and a torque parameter
    (RecursiveCheckpointAdjoint), against central differences; finite for a body at rest."""
    grad_fn = _check_gradients_against_central_differences(
        _final_attitude_loss(solver=jq.RKMK4(), dt0=0.01), "RecursiveCheckpointAdjoint"
    )
    at_rest = grad_fn(jnp.zeros(3), jnp.asarray(_GRAD_ARGS[1]), jnp.asarray(_GRAD_ARGS[2]))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in at_rest)


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_through_the_axis_splitting_match_finite_differences():
    """``RigidBodySplit``'s axis rotations (each from one half-angle ``sincos``, on components),
    torque-free, 30 steps of ``solve_fixed_steps``: grad of a final-attitude loss in omega0 and
    the moments against central differences (1e-6 relative to the largest entry), and finite for
    a body at rest (every rotation angle zero)."""
    target = jq.from_rotvec(jnp.asarray(_TARGET))

    def loss(w0, moments):
        term = diffrax.ODETerm(jq.RigidBody(jnp.diag(moments)))
        qs, _ = jq.solve_fixed_steps(
            jq.RigidBodySplit(), term, jnp.asarray([0.0, 1.5]), (jq.identity(), w0), substeps=30
        )
        return jnp.sum((qs[-1] - target) ** 2)

    args = tuple(jnp.asarray(a) for a in _GRAD_ARGS[:2])
    grad_fn, loss_fn = jax.jit(jax.grad(loss, argnums=(0, 1))), jax.jit(loss)
    for i, g in enumerate(grad_fn(*args)):
        fd = central_difference_jacobian(
            lambda x, i=i: loss_fn(*(x if k == i else a for k, a in enumerate(args))), np.asarray(args[i]), h=1e-6
        )
        scale = max(1e-3, float(np.abs(fd).max()))
        assert_close(np.asarray(g) / scale, fd / scale, tol=1e-6, what=f"gradient {i}")
    at_rest = grad_fn(jnp.zeros(3), args[1])
    assert all(np.all(np.isfinite(np.asarray(g))) for g in at_rest)


def test_batched_simulation_matches_single_runs_and_keeps_dtype():
    rng = np.random.default_rng(0)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(2, 3, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(2, 3, 3)), DTYPE)
    inertia = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    ts = jnp.linspace(0.0, 2.0, 5, dtype=DTYPE)
    sim = jq.simulate(q0, w0, inertia, ts, solver=jq.RKMK4(), dt0=0.01)
    assert sim.q.shape == (2, 3, 5, 4) and sim.omega.shape == (2, 3, 5, 3) and sim.q.dtype == DTYPE
    one = jq.simulate(q0[1, 2], w0[1, 2], inertia, ts, solver=jq.RKMK4(), dt0=0.01)
    assert_close(sim.q[1, 2], one.q, tol=1e-12 if X64 else 1e-5)
    norm_err = float(jnp.abs(jq.norm(sim.q) - 1).max())
    assert norm_err < (1e-13 if X64 else 1e-6), norm_err


def test_dense_output_stays_unit():
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(I_DIAG, DTYPE))))
    y0 = (jq.identity((), DTYPE), jnp.asarray(W0, DTYPE))
    sol = diffrax.diffeqsolve(
        term,
        jq.RKMK45(),
        0.0,
        5.0,
        0.1,
        y0,
        saveat=diffrax.SaveAt(dense=True),
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
    )
    qs = jnp.stack([sol.evaluate(t)[0] for t in np.linspace(0.05, 4.95, 7)])
    assert float(jnp.abs(jq.norm(qs) - 1).max()) < (1e-13 if X64 else 1e-6)


def test_euler_parameter_body_is_the_same_motion():
    """(q, qdot) with Chou's closed form under Tsit5 tracks (q, w) under RKMK45."""
    inertia = jnp.asarray([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 4.0]], DTYPE)
    q0, w0 = jq.identity((), DTYPE), jnp.asarray(W0, DTYPE)
    ep = jq.EulerParameterBody(inertia)
    qd0 = jq.qdot_from_omega(q0, w0)
    # The field is the library's function, to the bit, within one program (eagerly the field runs
    # operation by operation and the public function as one compiled program: 4e-19 apart).
    field_and_function = jax.jit(
        lambda q, qd: (ep(0.0, (q, qd), None)[1], jq.euler_parameter_acceleration(q, qd, inertia))
    )
    assert_close(*field_and_function(q0, qd0), tol=0)
    ts = jnp.linspace(0.0, 5.0, 6, dtype=DTYPE)
    tol = 1e-10 if X64 else 1e-5
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(ep),
        diffrax.Tsit5(),
        0.0,
        5.0,
        0.01,
        (q0, qd0),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
    )
    ref = jq.simulate(q0, w0, inertia, ts, rtol=tol, atol=tol)
    assert float(jnp.max(jq.angle_between(sol.ys[0], ref.q))) < (1e-8 if X64 else 1e-3)
    assert_close(jq.omega_from_qdot(sol.ys[0], sol.ys[1]), ref.omega, tol=1e-7 if X64 else 1e-3)


def test_bad_input():
    inertia = jnp.diag(jnp.asarray(I_DIAG))
    ts = jnp.linspace(0.0, 1.0, 3)
    with pytest.raises(ValueError, match="argument 'dt0' is required"):
        jq.simulate(jq.identity(), jnp.zeros(3), inertia, ts, solver=jq.RKMK4())
    full = inertia.at[0, 1].set(0.1).at[1, 0].set(0.1)
    with pytest.raises(Exception, match="needs the inertia in principal axes"):  # run-time check (eqx.error_if)
        diffrax.diffeqsolve(
            diffrax.ODETerm(jq.RigidBody(full)), jq.RigidBodySplit(), 0.0, 1.0, 0.1, (jq.identity(), jnp.ones(3))
        )
    with pytest.raises(ValueError, match=r"argument 'ts' must be shaped \(n,\)"):
        jq.simulate(jq.identity(), jnp.zeros(3), inertia, jnp.zeros(1))
    with pytest.raises(ValueError, match=r"argument 'omega0' must be a 3-vector array"):
        jq.simulate(jq.identity(), jnp.zeros(4), inertia, ts)
    with pytest.raises(ValueError, match="argument 'inertia'"):
        jq.simulate(jq.identity(), jnp.zeros(3), jnp.diag(jnp.asarray([1.0, 1.0, 3.0])), ts)


def _kicked_torque(t, q, w, args):
    """A torque of time, attitude and angular velocity (a damper): every kind of dependence."""
    return jnp.stack([0.1 * jnp.sin(t), 0.2 - 0.1 * q[..., 1], -0.3 * w[..., 0]], axis=-1)


@functools.lru_cache(maxsize=None)
def _kicked_reference():
    """The forced motion at t = 4 by RKMK45 at rtol = atol = 1e-13 (computed once for the four splittings)."""
    inertia = jnp.diag(jnp.asarray(I_DIAG))
    return jq.simulate(
        jq.identity(), jnp.asarray(W0), inertia, jnp.asarray([0.0, 4.0]), torque=_kicked_torque, rtol=1e-13, atol=1e-13
    ).q[-1]


@pytest.mark.skipif(not X64, reason="convergence orders are measured in float64")
@pytest.mark.parametrize("name", sorted(SPLITTINGS))
def test_splitting_order_with_a_torque(name):
    """With a torque of (t, q, w) the kicked splittings keep their stated order (the second
    half kick is the adjoint of the first, so the step stays symmetric)."""
    solver, order = SPLITTINGS[name]
    inertia = jnp.diag(jnp.asarray(I_DIAG))
    ts = jnp.asarray([0.0, 4.0])
    ref = _kicked_reference()
    dts = (0.02, 0.01) if order == 2 else (0.1, 0.05)
    errs = [
        float(
            jq.angle_between(
                jq.simulate(
                    jq.identity(), jnp.asarray(W0), inertia, ts, torque=_kicked_torque, solver=solver, dt0=dt
                ).q[-1],
                ref,
            )
        )
        for dt in dts
    ]
    measured = np.log2(errs[0] / errs[1])
    assert abs(measured - order) < 0.2, (name, errs, measured)


@pytest.mark.skipif(not X64, reason="accuracy bars are float64 figures")
def test_euler_poinsot_split_is_exact_without_torque_and_takes_full_tensors():
    """Torque-free, EulerPoinsotSplit is exact at any step: one step per saved interval over
    t = 100 matches DOP853 to 1e-10. simulate rotates a full tensor to principal axes (and
    back) for the splittings: same motion as RKMK45 on the full tensor."""
    ts = np.linspace(0.0, 100.0, 11)
    q_ref, w_ref = _dop853(100.0, ts)
    sim = jq.simulate(
        jq.identity(),
        jnp.asarray(W0),
        jnp.diag(jnp.asarray(I_DIAG)),
        jnp.asarray(ts),
        solver=jq.EulerPoinsotSplit(),
        dt0=10.0,
    )
    assert float(jnp.max(jq.angle_between(sim.q, jnp.asarray(q_ref)))) < 1e-10
    assert_close(sim.omega, w_ref, tol=1e-10, what="w")
    full = jnp.asarray([[2.0, 0.3, -0.1], [0.3, 2.5, 0.2], [-0.1, 0.2, 3.0]])
    ts = jnp.linspace(0.0, 10.0, 3)
    exact = jq.simulate(jq.identity(), jnp.asarray(W0), full, ts, solver=jq.EulerPoinsotSplit(), dt0=5.0)
    ref = jq.simulate(jq.identity(), jnp.asarray(W0), full, ts, rtol=1e-12, atol=1e-12)
    assert float(jnp.max(jq.angle_between(exact.q, ref.q))) < 1e-9
    assert_close(exact.omega, ref.omega, tol=1e-9, what="w, full tensor")


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_backsolve_adjoint_gradients():
    """BacksolveAdjoint: the forward pass with a Lie-group solver, the backward (augmented)
    pass with a generic solver, and with the same Lie solver (the mask then applies to the
    state part of the augmented state). Gradients in omega0, the inertia and a torque
    parameter agree with central differences to 1e-6 relative both ways."""
    backward = diffrax.BacksolveAdjoint(
        solver=diffrax.Tsit5(), stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-11)
    )
    loss = _final_attitude_loss(rtol=1e-11, atol=1e-11, adjoint=backward)
    values = jax.jit(loss)  # the adjoint changes only the gradient: one program for both
    _check_gradients_against_central_differences(loss, "BacksolveAdjoint", values)
    lie_backward = _final_attitude_loss(rtol=1e-11, atol=1e-11, adjoint=diffrax.BacksolveAdjoint())
    _check_gradients_against_central_differences(lie_backward, "BacksolveAdjoint with RKMK45 backward", values)


def test_the_adaptive_path_s_default_adjoint_keeps_64_checkpoints_per_body(monkeypatch):
    """``simulate``'s adaptive path passes ``diffeqsolve`` a ``RecursiveCheckpointAdjoint`` with 64
    checkpoints (``_CHECKPOINTS``: diffrax's own default, 446 for ``max_steps=100_000``, made the
    gradient of a batch 1.3-2x slower and twice as large in memory, each body of the ``vmap``
    holding its own), and a given adjoint is passed as it is. Gradients that recompute steps from
    checkpoints are checked against finite differences in ``test_lie_solvers.py``
    (``test_gradients_through_an_adaptive_solve_recomputing_from_checkpoints_...``)."""
    seen = []

    class Seen(Exception):
        pass

    def spy(*args, **kwargs):  # records the adjoint and stops: nothing is solved or compiled
        seen.append(kwargs["adjoint"])
        raise Seen

    monkeypatch.setattr(diffrax, "diffeqsolve", spy)
    q0, w0, inertia = jq.identity((2,), DTYPE), jnp.ones((2, 3), DTYPE), jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    ts = jnp.asarray([0.0, 0.5], DTYPE)
    for adjoint in (None, diffrax.RecursiveCheckpointAdjoint(checkpoints=5)):
        with pytest.raises(Seen):
            jq.simulate(q0, w0, inertia, ts, torque=_constant_torque, args=jnp.asarray(0.3, DTYPE), adjoint=adjoint)
    default, given = seen
    assert isinstance(default, diffrax.RecursiveCheckpointAdjoint) and default.checkpoints == 64
    assert isinstance(given, diffrax.RecursiveCheckpointAdjoint) and given.checkpoints == 5


def _spin_torque(t, q, w, args):
    return args * jnp.cross(w, jnp.asarray([0.0, 0.0, 1.0], w.dtype)) + 0.1 * jnp.sin(t)


@pytest.mark.parametrize("solver", [jq.RKMK4(), jq.LieEuler()], ids=["RKMK4", "LieEuler"])
def test_scan_path_matches_diffeqsolve(solver):
    """simulate's fixed-step lax.scan (the default for RKMK4/LieEuler with concrete ts; the
    struct-of-arrays step) against the same solver's own steps through diffrax.diffeqsolve (forced
    by passing an adjoint): per-body diagonal inertia and a body torque with args, then a full
    shared tensor and a space-frame torque; ts not a multiple of dt0 (17 equal steps of 0.5/17
    per interval)."""
    rng = np.random.default_rng(3)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(3, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(3, 3)), DTYPE)
    inertia = jnp.stack([jnp.diag(jnp.asarray(I_DIAG * s, DTYPE)) for s in (1.0, 1.5, 2.0)])
    ts = np.linspace(0.0, 2.0, 5)
    fast = jq.simulate(q0, w0, inertia, ts, torque=_spin_torque, args=0.3, solver=solver, dt0=0.03)
    slow = jq.simulate(
        q0,
        w0,
        inertia,
        ts,
        torque=_spin_torque,
        args=0.3,
        solver=solver,
        dt0=0.5 / 17,
        adjoint=diffrax.RecursiveCheckpointAdjoint(),
    )
    assert fast.solution is None and slow.solution is not None
    assert_close(fast.q, slow.q, tol=1e-11 if X64 else 2e-5, what="q")
    assert_close(fast.omega, slow.omega, tol=1e-11 if X64 else 2e-5, what="omega")
    # a full (not diagonal) shared tensor and a space-frame torque: the struct-of-arrays step's
    # other branches
    full = jq.to_matrix(q0[0]) @ inertia[1] @ jq.to_matrix(q0[0]).T
    fast, slow = (
        jq.simulate(q0, w0, full, ts, torque=_spin_torque, torque_frame="space", args=0.3, solver=solver, dt0=dt0, **kw)
        for dt0, kw in ((0.03, {}), (0.5 / 17, dict(adjoint=diffrax.RecursiveCheckpointAdjoint())))
    )
    assert_close(fast.q, slow.q, tol=1e-11 if X64 else 2e-5, what="q, full tensor")
    assert_close(fast.omega, slow.omega, tol=1e-11 if X64 else 2e-5, what="omega, full tensor")
    # the shared-tensor case (kept (3, 3) inside the scan) agrees with the broadcast one
    shared = jq.simulate(q0, w0, inertia[0], ts, solver=solver, dt0=0.03)
    broadcast = jq.simulate(q0, w0, jnp.broadcast_to(inertia[0], (3, 3, 3)), ts, solver=solver, dt0=0.03)
    assert_close(shared.q, broadcast.q, tol=1e-13 if X64 else 1e-6, what="shared inertia")


@pytest.mark.parametrize("solver", [jq.RKMK4(), jq.LieEuler()], ids=lambda s: type(s).__name__)
def test_a_time_dependent_torque_sees_a_scalar_time_on_the_scan_path(solver):
    """The torque's ``t`` is a scalar at every stage of the scan path, as on ``diffeqsolve``'s. The
    struct-of-arrays step handed it a time per body (the step size broadcast to the batch, session
    44 to 46): a law reading ``t`` failed for 5 bodies and, for 3, broadcast the times against its
    3 components without an error."""
    seen = set()

    def torque(t, q, w, k):
        seen.add(jnp.shape(t))
        return k * jnp.sin(3.0 * t) * jnp.asarray([1.0, -0.5, 0.25], w.dtype)

    q0 = jq.identity((5,), DTYPE)
    w0 = jnp.broadcast_to(jnp.asarray(W0, DTYPE), (5, 3))
    inertia, ts = jnp.diag(jnp.asarray(I_DIAG, DTYPE)), np.linspace(0.0, 1.0, 3)
    fast, slow = (
        jq.simulate(q0, w0, inertia, ts, torque=torque, args=0.7, solver=solver, dt0=0.05, **kw)
        for kw in ({}, dict(adjoint=diffrax.RecursiveCheckpointAdjoint()))
    )
    assert seen == {()}
    assert_close(fast.omega, slow.omega, tol=1e-11 if X64 else 2e-5, what="omega")


def _pd_on_rows(t, q, w, gains):
    return -gains[0] * q[..., 1:] - gains[1] * w + 0.1 * jnp.sin(t)


@functools.partial(jax.jit, static_argnames="layout")
def _one_step_and_gradient(w0, q0, layout):
    """One RKMK4 step of 0.05 s of 4 bodies under a PD torque in ``layout`` (``"components"``: the
    struct-of-arrays step, one loop per stage; ``"rows"``: the generic step on rows) and the
    gradient of a weighted sum of the attitudes it ends at, in ``w0``."""
    term = diffrax.ODETerm(jq.RigidBody(jnp.diag(jnp.asarray(I_DIAG, DTYPE)), _pd_on_rows))
    solver, gains = jq.RKMK4(layout=layout), jnp.asarray([50.0, 0.8], DTYPE)
    weights = jnp.asarray(np.linspace(-1.0, 1.0, 16).reshape(4, 4), DTYPE)

    def final(w):
        state = solver.init(term, 0.0, 0.05, (q0, w), gains)
        return solver.step(term, 0.0, 0.05, (q0, w), gains, state, False)[0][0]

    attitudes, pullback = jax.vjp(final, w0)  # one forward step for the value and the gradient
    return attitudes, pullback(weights)[0]


@pytest.mark.parametrize("fastest", [1.0, 100.0], ids=["all below the switch", "across it"])
def test_the_scan_path_s_stage_exponentials_choose_their_branch_by_the_batch(fastest):
    """With a torque the scan path's stage attitudes ``q Exp(theta_i)`` take the series alone when
    every body's ``|theta_i| / 2`` is below its switch, else the selection per element (a
    ``lax.cond``: ``struct_of_arrays._branches``). Both ways the final attitudes and their gradient
    in ``w0`` are those of the row layout's step, whose exponentials select per element: rates up
    to 1 rad/s (every ``|theta|`` below 0.05) and up to 100 rad/s (``|theta|`` up to 5, past the
    switch's 0.28), a step of 0.05 s, a stiff attitude gain (50) so that the stage attitudes show."""
    rng = np.random.default_rng(11)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(4, 4)), DTYPE))
    directions = rng.normal(size=(4, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    w0 = jnp.asarray(directions * np.asarray([0.2, 0.5, 0.8, fastest])[:, None], DTYPE)
    got, want = _one_step_and_gradient(w0, q0, "components"), _one_step_and_gradient(w0, q0, "rows")
    # measured (the gradient's entries up to 5): 5.6e-17 and 1.8e-15 (float64); with the series
    # taken when any body's angle is small, 1.9e-4 and 3e46 or NaN. Float32: this stiff step (gain
    # 50, angles up to 5) amplifies rounding, each layout is 2.8e-5 to 6.6e-5 from the float64 step
    # in the attitudes (1.2e-3 to 2.0e-3 in the gradient), and how close the two layouts land is
    # the machine's: 6.0e-8 and 2.9e-6 on AVX-512 CPUs, 2.5e-5 and 7.7e-4 with XLA limited to AVX
    # (session 58) and on a 2-core AMD EPYC with AVX2 and FMA but no AVX-512 (session 70, the
    # suite's emitters; 6.0e-8 and 1.4e-6 there under XLA's defaults). Until session 70 the bound
    # was 1e-6 and 5e-5 wherever XLA fuses multiply-adds, a verdict that moved with the CPU; the
    # float64 bounds carry the check, and in float32 the gradient's still catches the defect.
    assert_close(got[0], want[0], tol=1e-13 if X64 else 1e-4, what="attitudes")
    assert_close(got[1], want[1], tol=1e-12 if X64 else 3e-3, what="gradient in w0")


def test_the_lie_solvers_scan_path_is_the_struct_of_arrays_step(monkeypatch):
    """simulate's scan path runs LieEuler and RKMK4 on the struct-of-arrays step (whose reverse
    pass is element-wise) and the splittings on their own steps: a fresh shape (so the compiled
    solve is traced again) records which ran."""
    from jaxquat.integration import struct_of_arrays

    calls = []
    original = struct_of_arrays.solve
    monkeypatch.setattr(struct_of_arrays, "solve", lambda *a, **k: calls.append(a[0]) or original(*a, **k))
    q0 = jq.identity((5,), DTYPE)
    w0 = jnp.broadcast_to(jnp.asarray(W0, DTYPE), (5, 3))
    ts = np.linspace(0.0, 0.3, 6)
    for solver, expected in ((jq.RKMK4(), 4), (jq.LieEuler(), 1), (jq.RigidBodySplit(), None)):
        calls.clear()
        jq.simulate(q0, w0, jnp.diag(jnp.asarray(I_DIAG, DTYPE)), ts, solver=solver, dt0=0.01)
        assert [len(tab.b) for tab in calls] == ([] if expected is None else [expected]), type(solver).__name__


@pytest.mark.skipif(not X64, reason="a lowering test: its verdict does not depend on the dtype")
def test_the_scan_path_step_is_one_loop_per_stage_on_cpu():
    """The struct-of-arrays step's values go through one variadic ``reduce`` per stage but the last
    and one for the step's result (``jaxquat._fusion.one_loop``: one XLA loop each on CPU), with a
    torque two more per stage (the stage's components before the rows the torque takes, its
    components after), and in reverse mode one for the cotangents of the step's inputs; under
    ``jvp`` the values and their tangents share each loop (4, not 8); without ``one_loop`` none.
    The exponentials' conds (``struct_of_arrays._branches``): none in the torque-free forward
    pass, one per stage attitude with a torque, one for the last exponential's derivatives; each
    cond's argument through a loop of its own (``_safe._small_batch_parts``; for the last
    exponential, with the rotation vector it reads: ``_rotation._exp_derivatives_by_batch``). Counted in the
    lowered program (``jax.export``, no compilation)."""
    from jaxquat.integration import struct_of_arrays as soa

    comps = tuple(jnp.ones((8,), DTYPE) for _ in range(7))
    tab = soa.Tableau.of(jq.RKMK4.tableau, 4)

    def step(euler, one_loop, c):
        def field(t, q, w, args, entries):
            return w, euler.with_entries(entries)(t, q, w, args)

        q1, w1 = soa.rkmk_step(
            tab, field, 0.0, 0.01, c[:4], c[4:], None, euler.torque is not None, one_loop, euler.entries()
        )
        return q1 + w1

    def loops(fn):
        """(the one-loop barriers' reduces, the conds): each cond tests its batch by one reduce."""
        text = jax.export.export(jax.jit(fn), platforms=["cpu"])(comps).mlir_module()
        conds = text.count("stablehlo.case")
        return len(re.findall(r"stablehlo\.reduce\b(?!_)", text)) - conds, conds  # not reduce_precision

    inertia = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    free = soa.EulerEquations(inertia, None, True)
    pd = soa.EulerEquations(inertia, jax.vmap(lambda t, q, w, a: -q[1:] - w, in_axes=(None, 0, 0, None)), True)
    # the last exponential's value is selected per element (no cond), its derivatives by the batch
    assert loops(lambda c: step(free, True, c)) == (4, 0)
    assert loops(lambda c: step(free, False, c)) == (0, 0)
    # the three stage attitudes' exponentials choose their branch by the batch, value and derivatives
    assert loops(lambda c: step(pd, True, c)) == (4 + 2 * 4 + 3, 3)
    assert loops(lambda c: jax.jvp(functools.partial(step, free, True), (c,), (c,))) == (4 + 1, 1)
    assert loops(lambda c: jax.jvp(functools.partial(step, pd, True), (c,), (c,))) == (4 + 2 * 4 + 3 + 1, 3 + 1)

    def loss(one_loop):
        return lambda c: sum(jnp.sum(x) for x in step(free, one_loop, c))

    # the stages' loops (their values are the backward pass's residuals), the cotangents' loop and
    # the loop of the last exponential's cond argument; the result's loop and the loss's sums are
    # not needed for the gradient, so not lowered
    assert loops(jax.grad(loss(True))) == (3 + 1 + 1, 1)
    assert loops(jax.grad(loss(False))) == (1, 1)

    # a full tensor's gradient: its 12 entries (the six distinct ones of its symmetric part and of
    # its inverse) come out of a cotangents' loop of their own per body (12 operands) and are
    # summed over the batch after it; left out, each entry's sum was a reduction over the backward
    # step, and with the state's cotangents in one loop XLA wrote 18 entries out one by one
    def inertia_loss(tensor):
        return sum(jnp.sum(x) for x in step(soa.EulerEquations(tensor, None, False), True, comps))

    text = jax.export.export(jax.jit(jax.grad(inertia_loss)), platforms=["cpu"])(inertia).mlir_module()
    assert re.search(r"%\w+:12 = stablehlo\.reduce\(", text)


@pytest.mark.skipif(not X64, reason="a compiling test: its verdict does not depend on the dtype")
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the loops are reduces on CPU only")
@pytest.mark.parametrize("emitters", [True, False], ids=["fusion-emitters", "older-emitters"])
def test_the_scan_path_step_computes_what_its_loops_share_in_each(emitters):
    """``struct_of_arrays._recomputed``: in the gradient of one scan-path step (torque-free, RKMK4),
    the values a stage's loop shares with the cotangents' loop (the stage increments, ``I w``, the
    cross products) are computed in both instead of each being a kernel of its own, under either
    of XLA's CPU emitters (32 kernels against 14 with jaxlib 0.10.2); the same gradient. From
    jaxlib 0.11 XLA has the fusion emitters only (and no option to choose)."""
    from jaxquat.integration import struct_of_arrays as soa

    if not (XLA_CHOOSES_EMITTERS or emitters):
        pytest.skip("XLA of jaxlib 0.11 has no older emitters")
    options = {"xla_cpu_use_fusion_emitters": emitters} if XLA_CHOOSES_EMITTERS else None

    comps = tuple(jnp.linspace(0.1, 0.4, 8, dtype=DTYPE) * (1 + i) for i in range(7))
    tab = soa.Tableau.of(jq.RKMK4.tableau, 4)
    free = soa.EulerEquations(jnp.diag(jnp.asarray(I_DIAG, DTYPE)), None, True)

    def gradient(recompute):
        def loss(c):
            def field(t, q, w, args, entries):
                return w, free.with_entries(entries, recompute)(t, q, w, args)

            q1, w1 = soa.rkmk_step(tab, field, 0.0, 0.01, c[:4], c[4:], None, False, True, free.entries(), recompute)
            return sum(jnp.sum(x * x) for x in q1 + w1)

        return jax.jit(jax.grad(loss), compiler_options=options)

    def kernels(fn):
        text = fn.lower(comps).compile().as_text()
        return len(re.findall(r"^\s+(?:ROOT )?%\S+ = .* fusion\(", text, re.M))

    shared, recomputed = gradient(False), gradient(True)
    assert kernels(recomputed) <= kernels(shared) - 15
    for got, want in zip(recomputed(comps), shared(comps)):
        np.testing.assert_allclose(got, want, rtol=8 * np.finfo(np.float64).eps, atol=0)


def test_scan_path_gradient_and_unit_norm_in_float32_too():
    """Reverse mode through the scan path (jax.checkpoint per step) equals forward mode, torque-free
    and with a PD torque whose gains are in ``args`` (its rows and columns pass through the
    one-loop barriers of ``jaxquat._fusion``, whose derivative rules must serve both modes: the
    gains' gradients agree to 2.2e-16 in float64 and 3.6e-7 in float32, measured in session 43),
    and the per-step Newton renormalisation holds | |q| - 1 | at rounding level over 2000 steps."""
    inertia = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    q0 = jq.identity((), DTYPE)
    ts = np.asarray([0.0, 20.0])

    def loss(w0):
        return jnp.sum(jq.simulate(q0, w0, inertia, ts, solver=jq.RKMK4(), dt0=0.01).q[-1, 1:] ** 2)

    w0 = jnp.asarray(W0, DTYPE)
    rev = jax.grad(loss)(w0)
    fwd = jax.jacfwd(loss)(w0)
    assert_close(rev, fwd, tol=1e-9 if X64 else 1e-3, what="grad")

    def pd(t, q, w, gains):
        return -gains[0] * jnp.sign(q[0]) * q[1:] - gains[1] * w

    def controlled(gains):
        sim = jq.simulate(q0, w0, inertia, np.asarray([0.0, 2.0]), torque=pd, args=gains, solver=jq.RKMK4(), dt0=0.01)
        return jnp.sum(sim.q[-1, 1:] ** 2) + jnp.sum(sim.omega[-1] ** 2)

    gains = jnp.asarray([0.5, 0.3], DTYPE)
    assert_close(jax.grad(controlled)(gains), jax.jacfwd(controlled)(gains), tol=1e-9 if X64 else 1e-3, what="gains")
    q = jq.simulate(q0, jnp.asarray([0.3, -2.0, 1.1], DTYPE), inertia, ts, solver=jq.RKMK4(), dt0=0.01).q
    drift = float(jnp.abs(jq.norm(q) - 1).max())
    assert drift < (1e-14 if X64 else 5e-7), drift


def test_a_batch_larger_than_a_chunk_is_solved_chunk_by_chunk_with_the_same_values_and_derivatives(monkeypatch):
    """The scan path solves a batch of more than ``_CHUNK_BYTES`` per component array in chunks,
    one after another, each rematerialised in reverse mode (``numerical_solve._in_chunks``: at 10^5
    bodies the gradient's peak memory 3.2 -> 1.0 GB in float32). Here chunks of 3 bodies (10
    bodies: 4 chunks, the last padded with copies of the first body; 4 bodies here, 3 with a torque
    acting, ``_TORQUE_CHUNK``), and derivatives in chunks of 2 (``_DERIVATIVE_CHUNK``: at 10^5
    float32 bodies on one core the gradient 5.1 -> 2.7 s). The struct-of-arrays step sees batches
    of 4, 3 and 2, and the states, the gradient in the initial rates, the torque's gains (given in
    ``args``, and closed over by the torque: the solves are closure-converted) and the per-body
    inertia, and a ``jvp`` in the gains are those of the batch solved whole (LieEuler: the
    chunking does not depend on the tableau, and its one stage compiles fastest), and with one
    tensor shared by the batch the states too. The chunks are those of one thread here
    (``_threads.batch_multiple`` and ``pool_threads`` set to 1: no padding, ``_DERIVATIVE_CHUNK``),
    so the batches are those on any machine."""
    from jaxquat import _threads
    from jaxquat.integration import numerical_solve, struct_of_arrays

    monkeypatch.setattr(_threads, "batch_multiple", lambda: 1)
    monkeypatch.setattr(_threads, "pool_threads", lambda: 1)  # _DERIVATIVE_CHUNK, not its threads' size
    rng = np.random.default_rng(11)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(10, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(10, 3)), DTYPE)
    inertia = jnp.asarray(np.stack([np.diag(I_DIAG * s) for s in np.linspace(1.0, 2.0, 10)]), DTYPE)
    ts = np.linspace(0.0, 0.2, 3)

    def cost(w0, gains, inertia):
        sim = jq.simulate(q0, w0, inertia, ts, torque=_spin_torque, args=gains, solver=jq.LieEuler(), dt0=0.01)
        return jnp.sum(sim.q[:, -1, 1:] ** 2) + jnp.sum(jnp.sin(sim.omega[:, -1])), (sim.q, sim.omega)

    def closed_over(gains):  # the gains closed over by the torque, not handed in args
        torque = lambda t, q, w, args: _spin_torque(t, q, w, gains)  # noqa: E731
        sim = jq.simulate(q0, w0, inertia, ts, torque=torque, solver=jq.LieEuler(), dt0=0.01)
        return jnp.sum(sim.q[:, -1, 1:] ** 2)

    def run(w0, gains, inertia):
        (_, states), grads = jax.value_and_grad(cost, (0, 1, 2), has_aux=True)(w0, gains, inertia)
        tangents = jax.jvp(lambda g: cost(w0, g, inertia)[1], (gains,), (jnp.ones_like(gains),))[1]
        shared = jq.simulate(q0, w0, inertia[0], ts, solver=jq.LieEuler(), dt0=0.01)  # one (3, 3) tensor
        return states, grads, tangents, (shared.q, shared.omega), jax.grad(closed_over)(gains)

    gains = jnp.asarray(0.3, DTYPE)
    whole = run(w0, gains, inertia)
    batches = []
    original = struct_of_arrays.solve
    monkeypatch.setattr(struct_of_arrays, "solve", lambda *a, **k: batches.append(a[3].shape[0]) or original(*a, **k))
    monkeypatch.setattr(numerical_solve, "_CHUNK_BYTES", 4 * jnp.dtype(DTYPE).itemsize)
    monkeypatch.setattr(numerical_solve, "_TORQUE_CHUNK", 3)
    monkeypatch.setattr(numerical_solve, "_DERIVATIVE_CHUNK", 2)
    chunked = run(w0, gains, inertia)
    assert set(batches) == {2, 3, 4}, batches  # derivatives, values with the torque, torque-free values
    names = ["q", "omega", "grad w0", "grad gains", "grad inertia", "jvp q", "jvp omega", "shared q", "shared omega"]
    names += ["grad closed-over gains"]
    for a, b, what in zip(jax.tree.leaves(chunked), jax.tree.leaves(whole), names, strict=True):
        assert a.shape == b.shape, what
        assert_close(a, b, tol=1e-13 if X64 else 1e-6, what=what)


def test_steps_in_segments_give_the_same_states_and_derivatives(monkeypatch):
    """Past ``_SEGMENT_BYTES`` of states stored in reverse mode, ``scan_steps`` runs an interval's
    steps in segments of about ``sqrt(substeps)``, each rematerialised (at 1000 float64 bodies x
    1000 RKMK4 steps the gradient 78 -> 62 ms: its 56 MB of temporaries were mapped and faulted in
    at every call). Here 10 steps per interval (3 segments of 3, then 1), one interval and two: the
    states, the gradient in the initial state and in ``args``, and a ``jvp`` equal the unsegmented
    scan's to rounding, and the segments did run (a spy)."""
    from jaxquat import _trig
    from jaxquat.integration import fixed_step

    def step(y, t0, t1, args, jump):
        a, b = y
        h = t1 - t0
        return a + h * args * jnp.sin(b), b + h * jnp.cos(a) * (1 + t0)

    y0 = (jnp.asarray([0.3, -0.2, 1.1], DTYPE), jnp.asarray([0.5, 0.9, -0.4], DTYPE))
    gain = jnp.asarray(1.3, DTYPE)

    def run(ts):
        def final(y0, gain):
            ys = fixed_step.scan_steps(step, ts, y0, gain, substeps=10)
            return jnp.sum(ys[0] ** 2) + jnp.sum(jnp.sin(ys[1])), ys

        (_, ys), grads = jax.jit(jax.value_and_grad(final, (0, 1), has_aux=True))(y0, gain)
        tangent = jax.jit(lambda g: jax.jvp(lambda x: final(y0, x)[1], (g,), (jnp.ones_like(g),))[1])(gain)
        return ys, grads, tangent

    calls = []
    original = fixed_step._in_segments
    monkeypatch.setattr(fixed_step, "_in_segments", lambda *a: calls.append(a[3]) or original(*a))
    monkeypatch.setattr(_trig, "_cpu", lambda: True)  # the test is about the segments, not the platform
    for ts in (jnp.asarray([0.0, 1.0], DTYPE), jnp.asarray([0.0, 0.5, 1.0], DTYPE)):
        whole = run(ts)
        assert not calls
        monkeypatch.setattr(fixed_step, "_SEGMENT_BYTES", 0)
        segmented = run(ts)
        monkeypatch.setattr(fixed_step, "_SEGMENT_BYTES", 32 * 2**20)
        assert calls and set(calls) == {3}, calls
        calls.clear()
        for a, b in zip(jax.tree.leaves(segmented), jax.tree.leaves(whole), strict=True):
            assert_close(a, b, tol=1e-14 if X64 else 1e-6, what=f"{len(ts)} times")


def test_simulate_s_chunks_with_segmented_steps_are_not_rematerialised_and_agree(monkeypatch):
    """When a chunk's steps run in segments, ``simulate`` does not also rematerialise the chunk
    (a third forward pass). Chunks of 3 bodies with 20 LieEuler steps in segments of 4: the states,
    the gradient in ``w0`` and a ``jvp`` equal the batch's solved whole and unsegmented."""
    from jaxquat import _trig
    from jaxquat.integration import fixed_step, numerical_solve

    rng = np.random.default_rng(13)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(10, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(10, 3)), DTYPE)
    inertia = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    ts = np.asarray([0.0, 0.2])

    def states(w0):
        sim = jq.simulate(q0, w0, inertia, ts, torque=_spin_torque, args=0.3, solver=jq.LieEuler(), dt0=0.01)
        return sim.q, sim.omega

    def cost(w):
        q, omega = states(w)
        return jnp.sum(q[:, -1, 1:] ** 2) + jnp.sum(jnp.sin(omega)), (q, omega)

    def run():
        grad, values = jax.grad(cost, has_aux=True)(w0)
        return values, grad, jax.jvp(states, (w0,), (jnp.ones_like(w0),))[1]

    whole = run()
    segments, remats = [], []
    original_segments, original_chunks = fixed_step._in_segments, numerical_solve._in_chunks
    monkeypatch.setattr(fixed_step, "_in_segments", lambda *a: segments.append(a[3]) or original_segments(*a))
    monkeypatch.setattr(
        numerical_solve,
        "_in_chunks",
        lambda *a, remat, **k: remats.append(remat) or original_chunks(*a, remat=remat, **k),
    )
    monkeypatch.setattr(_trig, "_cpu", lambda: True)
    monkeypatch.setattr(fixed_step, "_SEGMENT_BYTES", 0)
    monkeypatch.setattr(numerical_solve, "_CHUNK_BYTES", 3 * jnp.dtype(DTYPE).itemsize)
    segmented = run()
    assert set(segments) == {4} and set(remats) == {False}, (segments, remats)
    for a, b in zip(jax.tree.leaves(segmented), jax.tree.leaves(whole), strict=True):
        assert_close(a, b, tol=1e-13 if X64 else 1e-6, what="segmented chunks")


@pytest.mark.skipif(not X64, reason="8 s a pass: the chunks' bookkeeping does not depend on the dtype")
def test_an_adaptive_batch_larger_than_a_chunk_is_solved_chunk_by_chunk_with_the_same_results(monkeypatch):
    """The adaptive path's vmapped solves run in chunks of at most ``_ADAPTIVE_CHUNK`` bodies (at
    10^4 PD-controlled bodies the gradient 1.7-2.1x faster: the chunk's arrays stay in cache).
    Chunks of 3 bodies (10 bodies, the last chunk padded): the states, each body's step count
    and the gradient in the torque's gains and the initial rates are the batch's solved whole
    (``diffrax.Heun``: the chunking does not depend on the solver, and its program is small)."""
    from jaxquat.integration import numerical_solve

    rng = np.random.default_rng(12)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(10, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(10, 3)), DTYPE)
    inertia = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    ts = np.linspace(0.0, 0.5, 3)

    def cost(w0, gains):
        sim = jq.simulate(
            q0, w0, inertia, ts, torque=_spin_torque, args=gains, solver=diffrax.Heun(), rtol=1e-4, atol=1e-4
        )
        value = jnp.sum(sim.q[:, -1, 1:] ** 2) + jnp.sum(jnp.sin(sim.omega[:, -1]))
        return value, (sim.q, sim.omega, sim.solution.stats["num_steps"])

    def run():  # a new function each call: traced again, not taken from jit's cache
        return jax.jit(lambda w0, g: jax.value_and_grad(cost, (0, 1), has_aux=True)(w0, g))(w0, jnp.asarray(0.3, DTYPE))

    (_, whole), whole_grads = run()
    monkeypatch.setattr(numerical_solve, "_ADAPTIVE_CHUNK", 3)
    (_, chunked), chunked_grads = run()
    steps = np.asarray(whole[2])
    assert steps.min() >= 3 and len(set(steps.tolist())) > 1, steps  # bodies take different steps
    np.testing.assert_array_equal(np.asarray(chunked[2]), steps)
    names = ["q", "omega", "grad w0", "grad gains"]
    for a, b, what in zip([*chunked[:2], *chunked_grads], [*whole[:2], *whole_grads], names, strict=True):
        assert a.shape == b.shape, what
        assert_close(a, b, tol=1e-13 if X64 else 1e-6, what=what)


def test_a_solve_with_a_progress_bar_takes_the_batch_whole(monkeypatch):
    """With ``progress=True`` the batch is not cut into chunks (one bar for the solve, not one a
    chunk); without it the adaptive path's chunks hold ``_ADAPTIVE_CHUNK`` bodies. A spy on
    ``_in_chunks`` records the chunk size and stops: nothing is solved or compiled."""
    from jaxquat.integration import numerical_solve

    sizes = spy_on_chunk_sizes(monkeypatch)
    monkeypatch.setattr(numerical_solve, "_ADAPTIVE_CHUNK", 2)
    q0, w0, inertia = jq.identity((5,), DTYPE), jnp.ones((5, 3), DTYPE), jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    for progress in (False, True):
        with pytest.raises(ChunkSeen):
            jq.simulate(q0, w0, inertia, np.linspace(0.0, 1.0, 3), torque=_spin_torque, args=0.3, progress=progress)
    assert sizes[0] == 2 and sizes[1] >= 5, sizes


def test_a_concrete_diagonal_tensor_is_taken_as_diagonal_under_a_user_s_jit(monkeypatch):
    """Whether the inertia is diagonal is asked of the tensor as given, not of its broadcast to the
    batch (a tracer under ``jit``): the closed form then runs without diagonalising each body
    (``_to_principal``), and the scan path's step reads only the moments; a full tensor is still
    diagonalised. Traced only (``lower``): nothing is compiled."""
    from jaxquat.integration import principal_frame, struct_of_arrays

    seen = []
    to_principal, euler = principal_frame.to_principal, struct_of_arrays.EulerEquations
    monkeypatch.setattr(principal_frame, "to_principal", lambda *a: seen.append("principal") or to_principal(*a))
    monkeypatch.setattr(
        struct_of_arrays,
        "EulerEquations",
        lambda i, t, diagonal, **kw: seen.append(diagonal) or euler(i, t, diagonal, **kw),
    )
    q0, w0 = jq.identity((5,), DTYPE), jnp.ones((5, 3), DTYPE)
    diagonal = jnp.diag(jnp.asarray(I_DIAG, DTYPE))
    rotation = jq.to_matrix(jq.normalize(jnp.asarray([1.0, 0.2, -0.3, 0.4], DTYPE)))
    ts = np.linspace(0.0, 0.2, 3)
    for n, (inertia, kw) in enumerate(
        (
            (diagonal, {}),
            (diagonal, dict(solver=jq.RKMK4(), dt0=0.1)),
            (np.diag(np.asarray(I_DIAG, DTYPE)), {}),  # NumPy under jit: jnp.asarray would make it a tracer
            (np.diag(np.asarray(I_DIAG, DTYPE)), dict(solver=jq.RKMK4(), dt0=0.1)),
            (rotation @ diagonal @ rotation.T, {}),
        ),
        start=5,
    ):  # a batch size each: simulate's inner jit would otherwise reuse a trace of the same shapes
        jax.jit(functools.partial(lambda q, w, i, kw: jq.simulate(q, w, i, ts, **kw).q, i=inertia, kw=kw)).lower(
            q0[:1].repeat(n, 0), w0[:1].repeat(n, 0)
        )
    assert seen == [True, True, "principal"], seen


def test_the_scan_path_gradient_in_a_full_tensor_is_symmetric():
    """The scan path's step reads a full tensor's symmetric part (``EulerEquations``: 12 entries
    in a loop of their own, 2.4-5.6x faster than 18), so its gradient with respect to the tensor
    is symmetric to the bit, and equals the symmetric part of the generic path's (``diffeqsolve``
    on the rows, which reads all nine entries): the same derivative along any symmetric change,
    which ``jvp`` gives too."""
    rng = np.random.default_rng(4)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(3, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(3, 3)), DTYPE)
    rotation = jq.to_matrix(jq.normalize(jnp.asarray([1.0, 0.2, -0.3, 0.4], DTYPE)))
    tensor = rotation @ jnp.diag(jnp.asarray(I_DIAG, DTYPE)) @ rotation.T
    tensor = 0.5 * (tensor + tensor.T)
    ts, weights = np.linspace(0.0, 0.5, 3), jnp.arange(1.0, 5.0, dtype=DTYPE)

    def loss(tensor, **kw):
        sim = jq.simulate(q0, w0, tensor, ts, torque=_spin_torque, args=0.3, solver=jq.RKMK4(), dt0=0.05, **kw)
        return jnp.sum(sim.q[:, -1] * weights[None]) + jnp.sum(sim.omega[:, -1] ** 2)

    scan = jax.jit(jax.grad(loss))(tensor)
    generic = jax.jit(jax.grad(lambda t: loss(t, adjoint=diffrax.RecursiveCheckpointAdjoint())))(tensor)
    np.testing.assert_array_equal(scan, scan.T)
    assert_close(scan, 0.5 * (generic + generic.T), tol=1e-12 if X64 else 2e-5)
    direction = jnp.asarray(rng.normal(size=(3, 3)), DTYPE)
    direction = direction + direction.T
    along = jax.jit(lambda t, d: jax.jvp(loss, (t,), (d,))[1])(tensor, direction)
    assert_close(along, jnp.sum(scan * direction), tol=1e-12 if X64 else 2e-5)


def test_a_concrete_inertia_is_checked_under_a_user_s_jit():
    """A NumPy tensor handed to ``simulate`` inside ``jit`` has known values: they are checked as
    in an eager call (``jnp.asarray`` would have made it a tracer, and the check was skipped)."""
    q0, w0 = jq.identity((2,), DTYPE), jnp.ones((2, 3), DTYPE)
    bad = np.diag(np.asarray([1.0, 2.0, 5.0], DTYPE))
    with pytest.raises(ValueError, match="argument 'inertia' violates the triangle inequality"):
        jax.jit(lambda q, w: jq.simulate(q, w, bad, np.linspace(0.0, 0.2, 3)).q).lower(q0, w0)


# A learned torque (an MLP with its weights in ``args``) and an element-wise PD law (its gains in
# ``args``) under XLA's default flags, in float64: the suite's own processes compile with the
# legacy emitters (tests/conftest.py), which hid the defects this checks. The scan path's
# backward step compiled (fusion emitters) to a kernel of 0.65 s per step for 16 bodies with the
# MLP, and of about 0.48 s per step with the PD law (struct_of_arrays.columns_by_products), so
# either 1000-step gradient would take minutes; and diffrax 0.7.1-0.7.2 returned a gradient
# 2.6 % off under jit on the diffeqsolve path (ConstantStepSize, SaveAt(ts), the default adjoint).
LEARNED_TORQUE_SCRIPT = r"""
import os
os.environ.pop("XLA_FLAGS", None)
import jax
jax.config.update("jax_enable_x64", True)
import diffrax, jax.numpy as jnp, numpy as np
import jaxquat as jq

n, steps = 16, 1000
ts = np.linspace(0.0, 0.05 * steps, steps + 1)
inertia = jnp.diag(jnp.asarray([1.0, 1.5, 2.0]))
k = jax.random.split(jax.random.PRNGKey(0), 5)
params = [(jax.random.normal(k[0], (6, 8)) / 3, jnp.zeros(8)), (jax.random.normal(k[1], (8, 3)) / 3, jnp.zeros(3))]
q0, w0 = jq.random(k[2], (n,)), 0.2 * jax.random.normal(k[3], (n, 3))

def torque(t, q, w, p):
    h = jnp.tanh(jnp.concatenate([q[1:], w]) @ p[0][0] + p[0][1])
    return jnp.tanh(h @ p[1][0] + p[1][1])

def cost(p, **kw):
    sim = jq.simulate(q0, w0, inertia, ts, torque=torque, args=p, solver=jq.RKMK4(), dt0=0.05, **kw)
    return jnp.mean(jnp.sum(sim.q[..., 1:] ** 2, -1)) + 0.1 * jnp.mean(jnp.sum(sim.omega**2, -1))

d = jax.tree.map(lambda x: jax.random.normal(k[4], x.shape), params)
step = lambda e: jax.tree.map(lambda x, y: x + e * y, params, d)
# one compiled program per path: its values at +-1e-6 give the central difference
for path, kw in [("scan", {}), ("diffeqsolve", dict(adjoint=diffrax.RecursiveCheckpointAdjoint()))]:
    value_and_grad = jax.jit(jax.value_and_grad(lambda p: cost(p, **kw)))
    fd = (value_and_grad(step(1e-6))[0] - value_and_grad(step(-1e-6))[0]) / 2e-6
    g = value_and_grad(params)[1]
    print(path, float(sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d)))), float(fd))

# an element-wise law: PD on the error to a target attitude, the gains in args (scan path)
target = jq.random(k[4], ())

def pd(t, q, w, gains):
    e = jq.multiply(jq.conjugate(target), q)
    return -gains[0] * jnp.sign(e[0]) * e[1:] - gains[1] * w

def pd_cost(gains):
    sim = jq.simulate(q0, w0, inertia, ts, torque=pd, args=gains, solver=jq.RKMK4(), dt0=0.05)
    return jnp.mean(jnp.sum(sim.q[..., 1:] ** 2, -1)) + 0.1 * jnp.mean(jnp.sum(sim.omega**2, -1))

gains, dg = jnp.asarray([0.3, 0.5]), jnp.asarray([0.6, -0.8])
value_and_grad = jax.jit(jax.value_and_grad(pd_cost))
fd = (value_and_grad(gains + 1e-6 * dg)[0] - value_and_grad(gains - 1e-6 * dg)[0]) / 2e-6
print("elementwise", float(jnp.vdot(value_and_grad(gains)[1], dg)), float(fd))
"""


@pytest.mark.skipif(X64, reason="once per make test, in the shorter float32 pass (the script runs in float64)")
def test_gradient_of_a_learned_torque_under_xla_defaults_matches_finite_differences():
    """``jit(grad)`` through ``simulate`` of a cost of 16 bodies over 1000 RKMK4 steps, the torque
    an MLP of the state with its weights in ``args``, on the scan path and through
    ``diffeqsolve``, and a PD law on the scan path, against a central difference along a random
    direction of the weights or gains (measured 6.2e-9 and 7.1e-9 relative on the two MLP paths,
    2.1e-9 for the PD law, the central difference's own error; the bound 1e-6), the differences
    from the values of the same compiled ``value_and_grad`` (eager costs for the differences, one
    for the MLP shared by both paths and one for the PD law, compiled programs of their own: 17.8 s
    against 16.1-16.6 s for the script). The 240 s limit of the
    subprocess catches the slow kernels (about 750 s and 480 s)."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_ENABLE_X64")}
    # From a deep frame, as the suite's tests run (tests/frames.py): on one pinned core of a 2-core
    # Intel Xeon, two runs each, alternated, 19.5 -> 18.4-18.5 s and 252 000 -> 163 000 page faults.
    script = script_in_deep_frame(LEARNED_TORQUE_SCRIPT)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=240)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = dict(line.split(maxsplit=1) for line in out.stdout.splitlines())
    assert set(lines) == {"scan", "diffeqsolve", "elementwise"}, out.stdout
    for path, pair in lines.items():
        ad, fd = (float(x) for x in pair.split())
        assert abs(ad - fd) <= 1e-6 * abs(fd), (path, ad, fd)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(ts=[1.0, 0.0]), ValueError, "'ts' must be finite and strictly increasing"),
        (dict(ts=[0.0, 2.0, 1.0]), ValueError, "'ts' must be finite and strictly increasing"),
        (dict(ts=[0.0, 1.0, 1.0]), ValueError, "'ts' must be finite and strictly increasing"),
        (dict(ts=[0.0, np.nan]), ValueError, "'ts' must be finite and strictly increasing"),
        (dict(ts=[0.0, np.inf]), ValueError, "'ts' must be finite and strictly increasing"),
        (dict(solver=jq.RKMK4(), dt0=0.0), ValueError, "'dt0' must be a finite positive step size"),
        (dict(solver=jq.RKMK4(), dt0=np.nan), ValueError, "'dt0' must be a finite positive step size"),
        (dict(solver=jq.RKMK4(), dt0=-0.1), ValueError, "'dt0' must be a finite positive step size"),
        (dict(solver="RKMK4", dt0=0.1), TypeError, "'solver' must be a diffrax solver instance"),
    ],
)
def test_simulate_rejects_bad_times_steps_and_solvers(kwargs, error, match):
    args = dict(ts=[0.0, 1.0])
    args.update(kwargs)
    ts = jnp.asarray(args.pop("ts"), DTYPE)
    with pytest.raises(error, match=match):
        jq.simulate(
            jnp.asarray([1.0, 0, 0, 0], DTYPE),
            jnp.asarray([0.1, 1.0, 0.1], DTYPE),
            jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE)),
            ts,
            **args,
        )


def test_simulate_checks_a_traced_ts_at_run_time():
    q0, w0 = jnp.asarray([1.0, 0, 0, 0], DTYPE), jnp.asarray([0.1, 1.0, 0.1], DTYPE)
    run = jax.jit(lambda ts: jq.simulate(q0, w0, jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE)), ts).q)
    assert np.all(np.isfinite(np.asarray(run(jnp.asarray([0.0, 1.0], DTYPE)))))
    with pytest.raises(Exception, match="'ts' must be finite and strictly increasing"):
        run(jnp.asarray([1.0, 0.0], DTYPE)).block_until_ready()


FULL_TENSOR = np.array([[2.0, 0.1, 0.0], [0.1, 1.5, 0.2], [0.0, 0.2, 1.0]])


def test_default_torque_free_simulate_is_the_closed_form_at_every_saved_time():
    """The default torque-free path evaluates euler_poinsot from the initial state at each ts; it
    agrees with the same flow stepped through diffeqsolve (StepTo(ts), chosen by passing an
    adjoint), with a full tensor through principal axes and with a batch."""
    q0 = jnp.asarray(jq.random(jax.random.PRNGKey(3), (2, 3)), DTYPE)
    w0 = jnp.asarray(np.random.default_rng(3).normal(size=(2, 3, 3)), DTYPE)
    ts = jnp.linspace(0.0, 20.0, 9, dtype=DTYPE)
    direct = jq.simulate(q0, w0, jnp.asarray(FULL_TENSOR, DTYPE), ts)
    assert direct.solution is None and direct.q.shape == (2, 3, 9, 4) and direct.omega.shape == (2, 3, 9, 3)
    stepped = jq.simulate(q0, w0, jnp.asarray(FULL_TENSOR, DTYPE), ts, adjoint=diffrax.RecursiveCheckpointAdjoint())
    tol = 1e-12 if X64 else 2e-4  # measured 2e-14 / 1.8e-5 (the stepped flow chains the rounding)
    assert float(jnp.max(jq.angle_between(direct.q, stepped.q))) < tol  # q and -q are one rotation
    assert_close(direct.omega, stepped.omega, tol=tol, what="rates")


def test_default_torque_free_simulate_forms_each_body_once_for_all_its_saved_times():
    """The closed-form path forms each body's part of the solution once and evaluates it at all
    its saved times; the result is euler_poinsot evaluated element by element over the broadcast
    (body, time) batch, to rounding (measured 5.3e-15 / 3.0e-6: two compiled programs), for six
    bodies with different states and times starting before zero. The call runs one compiled
    program, and so does the scan path's: the shared tensor is not broadcast to the batch first
    (an eager operation of its own until session 63, 24 ms of a first call of 1.5 s; the batch
    shape (3, 2) is this test's own, so that no earlier test has compiled that broadcast)."""
    q0 = jnp.asarray(jq.random(jax.random.PRNGKey(3), (3, 2)), DTYPE)
    w0 = jnp.asarray(np.random.default_rng(3).normal(size=(3, 2, 3)), DTYPE)
    ts = jnp.linspace(-5.0, 20.0, 9, dtype=DTYPE)
    moments = jnp.asarray([1.0, 2.0, 3.0], DTYPE)
    inertia = jnp.diag(moments)
    with lowered_programs() as names:
        direct = jq.simulate(q0, w0, inertia, ts)
        jq.simulate(q0, w0, inertia, ts, solver=jq.RKMK4(), dt0=3.125)  # the scan path: one step per interval
    assert set(names) <= {"jit(_exact_simulate)", "jit(_solve_body)"}, names
    q, w = jq.euler_poinsot(q0[..., None, :], w0[..., None, :], moments, ts - ts[0])
    tol = 1e-13 if X64 else 2e-5
    assert_close(direct.q, q, tol=tol, what="attitudes")
    assert_close(direct.omega, w, tol=tol, what="rates")


def test_default_torque_free_simulate_keeps_unit_norm_over_many_saved_times():
    """Float32, 10^4 saved times: chained from each saved time to the next the norm drifted to 2.2e-4;
    evaluated from the initial state it stays at rounding level."""
    ts = jnp.linspace(0.0, 1000.0, 10_001, dtype=DTYPE)
    r = jq.simulate(
        jnp.asarray([1.0, 0, 0, 0], DTYPE),
        jnp.asarray([0.1, 1.0, 0.1], DTYPE),
        jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE)),
        ts,
    )
    deviation = float(jnp.max(jnp.abs(jnp.linalg.norm(r.q, axis=-1) - 1)))
    assert deviation < (1e-13 if X64 else 1e-6)


@pytest.mark.skipif(
    not X64,
    reason="the derivative rules do not depend on the dtype: checked once, in float64, at 5 digits tighter "
    "tolerance (float32: 25 s of compiling for a 2e-3 check; test_scan_path_gradient_and_unit_norm_in_float32_too "
    "keeps a float32 gradient)",
)
def test_forward_mode_through_simulate():
    """jacfwd works on the closed-form path as it is, and on diffeqsolve with ForwardMode; without
    it the error names the adjoint to pass. Checked against central differences of the forward
    map (step 1e-5 in float64, 1e-2 in float32), and on the closed-form path reverse mode too, at
    a generic state and on the separatrix."""
    q0, w0 = jnp.asarray([1.0, 0, 0, 0], DTYPE), jnp.asarray([0.1, 1.0, 0.1], DTYPE)
    inertia = jnp.diag(jnp.asarray([1.0, 2.0, 3.0], DTYPE))
    ts = jnp.asarray([0.0, 1.0], DTYPE)

    def torque(t, q, w, args):
        return jnp.asarray([0.1, 0.0, -0.05], DTYPE) * jnp.cos(t)

    def forced(adjoint):  # diffeqsolve (an adjoint is given), fixed steps to keep the compile short
        return lambda w: jq.simulate(q0, w, inertia, ts, torque=torque, adjoint=adjoint, solver=jq.RKMK4(), dt0=0.05).q[
            -1
        ]

    with pytest.raises(TypeError, match=r"adjoint=diffrax\.ForwardMode\(\)"):
        jax.jacfwd(forced(diffrax.RecursiveCheckpointAdjoint()))(w0)
    h = 1e-5 if X64 else 1e-2

    def final(w, inertia):
        return jq.simulate(q0, w, inertia, ts).q[-1]

    closed_form = jax.jit(final)
    jac_closed_form = jax.jit(jax.jacfwd(final))
    grad_closed_form = jax.jit(jax.grad(lambda w, inertia: final(w, inertia)[1]))
    # The second state is on the separatrix (|L|^2 = 2 E I_mid), where both modes gave NaN.
    for w, inertia_ in (
        (w0, inertia),
        (jnp.asarray([2.0, 0.5, 1.0], DTYPE), jnp.diag(jnp.asarray([3.0, 4.0, 6.0], DTYPE))),
    ):
        fd = jnp.stack(
            [
                (closed_form(w + h * e, inertia_) - closed_form(w - h * e, inertia_)) / (2 * h)
                for e in jnp.eye(3, dtype=DTYPE)
            ],
            -1,
        )
        assert_close(jac_closed_form(w, inertia_), fd, tol=1e-8 if X64 else 2e-3, what=f"jacfwd vs differences at {w}")
        assert_close(
            grad_closed_form(w, inertia_), fd[1], tol=1e-8 if X64 else 2e-3, what=f"grad vs differences at {w}"
        )
    f = forced(diffrax.ForwardMode())
    value = jax.jit(f)
    fd = jnp.stack([(value(w0 + h * e) - value(w0 - h * e)) / (2 * h) for e in jnp.eye(3, dtype=DTYPE)], -1)
    assert_close(jax.jit(jax.jacfwd(f))(w0), fd, tol=1e-8 if X64 else 2e-3, what="jacfwd vs central differences")


@pytest.mark.parametrize("solver", [jq.RigidBodySplit(), jq.EulerPoinsotSplit()], ids=lambda s: type(s).__name__)
def test_splittings_keep_unit_norm_and_the_invariants_over_many_steps_torque_free(solver):
    """10^5 torque-free steps of h = 0.01 from three states (one near a steady spin about the
    major axis, where each step's rounding repeats and drifted linearly: float32 relative
    drift of |m|^2 and 2E 7.7e-3 and 2.2e-3 before the projection onto the initial
    invariants; 2.4e-7 after, and 1e-6 after 10^6 steps). In float64 RigidBodySplit restores
    only |m| (its energy error is the splitting's bounded O(h^2) one, 6.7e-7 here). Each step
    also ends with the Newton renormalisation of q, so float32 rounding of |q| does not walk
    (without it 2.3e-4 and 2.1e-3 after 10^5 steps; with it 1.2e-7)."""
    moments = jnp.asarray([1.0, 2.0, 3.0], DTYPE)
    w0 = jnp.asarray([[0.05, 0.02, 1.0], [1.0, 0.3, 0.2], [0.1, 1.0, 0.1]], DTYPE)
    r = jq.simulate(
        jnp.asarray([1.0, 0, 0, 0], DTYPE),
        w0,
        jnp.diag(moments),
        jnp.linspace(0.0, 1000.0, 11, dtype=DTYPE),
        solver=solver,
        dt0=0.01,
        max_steps=100_010,
    )
    m = moments[None, None] * r.omega
    casimir, energy = jnp.sum(m * m, -1), jnp.sum(m * r.omega, -1)
    casimir_drift = float(jnp.max(jnp.abs(casimir / casimir[:, :1] - 1)))
    energy_drift = float(jnp.max(jnp.abs(energy / energy[:, :1] - 1)))
    assert casimir_drift < (1e-13 if X64 else 1e-6), casimir_drift
    bound = 1e-13 if X64 and isinstance(solver, jq.EulerPoinsotSplit) else (1e-5 if X64 else 1e-6)
    assert energy_drift < bound, energy_drift
    assert float(jnp.max(jnp.abs(jnp.linalg.norm(r.q, axis=-1) - 1))) < (1e-13 if X64 else 1e-6)


def test_progress_without_tqdm_names_the_optional_dependency(monkeypatch):
    """tqdm is optional (``jaxquat[progress]``): without it ``progress=True`` says what to install."""
    import sys

    monkeypatch.setitem(sys.modules, "tqdm", None)  # import tqdm raises ImportError
    with pytest.raises(ImportError, match=r"simulate\(progress=True\) needs tqdm.*jaxquat\[progress\]"):
        jq.simulate(
            jnp.asarray([1.0, 0, 0, 0], DTYPE),
            jnp.asarray([0.1, 1.0, 0.1], DTYPE),
            jnp.eye(3, dtype=DTYPE),
            jnp.asarray([0.0, 1.0], DTYPE),
            progress=True,
        )
    with pytest.raises(ImportError, match=r"minimum_time_reorientation\(progress=True\) needs tqdm"):
        jq.minimum_time_reorientation(
            jnp.eye(3, dtype=DTYPE),
            jnp.ones(3, DTYPE),
            jnp.asarray([1.0, 0, 0, 0], DTYPE),
            jnp.asarray([0.0, 1.0, 0, 0], DTYPE),
            progress=True,
            method="single_shooting",
        )


def _concatenated_operands(n_times: int) -> int:
    """Operands of every concatenation in the lowered program of an adaptive ``simulate`` with
    ``n_times`` saved times (traced), summed."""
    ts = jnp.linspace(0.0, 1.0, n_times, dtype=DTYPE)
    fn = jax.jit(lambda w, ts: jq.simulate(jq.identity((), DTYPE), w, jnp.eye(3, dtype=DTYPE), ts, solver=jq.RKMK45()))
    text = fn.lower(jnp.ones(3, DTYPE), ts).as_text()
    return sum(line.split("dim =")[0].count("%") - 1 for line in text.splitlines() if "stablehlo.concatenate" in line)


def test_adaptive_simulate_compiles_no_concatenation_of_every_saved_time():
    """Diffrax 0.7.0 fills ``SaveAt(ts=...)`` on its ``t0 == t1`` branch by stacking ``len(ts)``
    copies of the state, which XLA on CPU compiled into kernels of megabytes (6001 saved times:
    21 s of the first call's 22 s). ``simulate`` traces it as a broadcast: the program's
    concatenations do not grow with the number of saved times (with the stack: 4320 operands at
    2001 times, 50 without). The broadcast's values are the stack's."""
    assert _concatenated_operands(2001) == _concatenated_operands(101)
    from jaxquat.integration.numerical_solve import _StackOfCopiesAsBroadcast

    shim = _StackOfCopiesAsBroadcast(jnp)
    x = jnp.arange(6.0, dtype=DTYPE).reshape(2, 3)
    np.testing.assert_array_equal(shim.stack([x] * 5), jnp.stack([x] * 5))
    np.testing.assert_array_equal(shim.stack([x, x + 1]), jnp.stack([x, x + 1]))
    assert shim.pi == jnp.pi


@pytest.mark.skipif(not X64, reason="a float64 torque on a float32 state needs x64")
def test_a_torque_in_another_dtype_is_taken_in_the_state_s():
    """A torque law returning float64 for a float32 state: the scan path and the adaptive path
    (the Lie solvers' component step) take it in the state's dtype, as the generic step's term
    does, instead of failing on the loop's carry types (both did until session 44)."""
    q0 = jq.random(jax.random.PRNGKey(1), (4,), jnp.float32)
    w0 = jnp.ones((4, 3), jnp.float32)
    inertia = jnp.diag(jnp.asarray(I_DIAG, jnp.float32))

    def torque(t, q, w, args):
        return jnp.asarray([0.1, 0.0, 0.0], jnp.float64) - 0.1 * w

    ts = np.asarray([0.0, 1.0])
    fixed = jq.simulate(q0, w0, inertia, ts, torque=torque, solver=jq.RKMK4(), dt0=0.01)
    adaptive = jq.simulate(q0, w0, inertia, ts, torque=torque, rtol=1e-6, atol=1e-6)
    for run in (fixed, adaptive):
        assert run.q.dtype == jnp.float32 and run.omega.dtype == jnp.float32
    assert_close(fixed.q[:, -1], adaptive.q[:, -1], tol=1e-5)  # measured 8.8e-7


def test_an_interval_of_whole_steps_up_to_the_rounding_of_ts_takes_that_many_steps():
    """The scan path splits each interval into ``ceil(interval / dt0)`` steps, up to the rounding
    of ``ts`` in the solve's dtype: float32 0.1 is 0.10000000149, which with ``dt0=0.05`` took 3
    steps an interval before session 69 (``LieEuler``'s float32 states 1.1e-3 from float64's).
    ``_scan_substeps`` directly, then ``simulate``'s scan path against ``diffeqsolve``'s (an
    adjoint given: diffrax steps by ``dt0`` itself), which agree to rounding only with the same
    steps (first order: 2 or 3 steps differ by 1e-3 here)."""
    import diffrax

    from jaxquat.integration import numerical_solve

    ts32 = np.asarray([0.0, 0.1, 0.2], np.float32).astype(np.float64)
    solver = jq.LieEuler()
    assert numerical_solve._scan_substeps(solver, ts32, 0.05, None, np.dtype(np.float32)) == 2
    assert numerical_solve._scan_substeps(solver, np.asarray([0.0, 0.1, 0.2]), 0.05, None, np.dtype(np.float64)) == 2
    assert numerical_solve._scan_substeps(solver, np.asarray([0.0, 0.1 + 1e-9]), 0.05, None, np.dtype(np.float64)) == 3
    big = np.asarray([1000.0, 1000.1], np.float32).astype(np.float64)  # interval 0.0999756 in float32
    assert numerical_solve._scan_substeps(solver, big, 0.05, None, np.dtype(np.float32)) == 2
    assert numerical_solve._scan_substeps(solver, big, 0.04, None, np.dtype(np.float32)) == 3

    rng = np.random.default_rng(4)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(4, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(4, 3)), DTYPE)
    inertia, ts = np.diag(I_DIAG).astype(DTYPE), np.asarray([0.0, 0.1, 0.2], DTYPE)
    scan = jq.simulate(q0, w0, inertia, ts, solver=solver, dt0=0.05)
    stepped = jq.simulate(q0, w0, inertia, ts, solver=solver, dt0=0.05, adjoint=diffrax.RecursiveCheckpointAdjoint())
    assert int(stepped.solution.stats["num_steps"]) == 4
    assert_close(scan.q, stepped.q, tol=1e-13 if X64 else 1e-6, what="q")
    assert_close(scan.omega, stepped.omega, tol=1e-13 if X64 else 1e-6, what="omega")
