"""The multiple-shooting interior-point layer: solve_shooting against SciPy on a small NLP, the
minimum-energy slew against its closed form, every constraint on a 10x finer re-simulation,
the minimum-time certificate (switching function against the torque), batching, bad input.

The interior-point method converges to a KKT error of 1e-9 and needs float64; these run in
the float64 pass. Each configuration compiles once (about 15 s): the problems are shared by
module fixtures and kept to few intervals."""

from __future__ import annotations

import functools
import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

import jaxquat as jq
from jaxquat.control.optimal_control import check_tolerance, float64_hint
from helpers import X64, XLA_CHOOSES_EMITTERS, lowered_programs, run_example_in_process, run_notebook_in_process

pytestmark = pytest.mark.skipif(not X64, reason="the interior-point method converges to 1e-9 in float64 only")

N = 12
Q0 = np.array([1.0, 0.0, 0.0, 0.0])
AXIS = np.array([1.0, 2.0, 2.0]) / 3.0
THETA = np.pi / 2
QF = np.concatenate([[np.cos(THETA / 2)], np.sin(THETA / 2) * AXIS])
QZ = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 degrees about z


def _resimulate(inertia, q0, w0, controls, time, substeps):
    """The returned torque re-integrated with ``substeps`` RKMK4 steps per interval (NumPy)."""
    qs, ws = _resimulated(jnp.asarray(inertia), jnp.asarray(q0), jnp.asarray(w0), jnp.asarray(controls), time, substeps)
    return np.asarray(qs), np.asarray(ws)


@functools.partial(jax.jit, static_argnames="substeps")
def _resimulated(inertia, q0, w0, controls, time, substeps):
    """:func:`_resimulate`'s program, the body and the torque its arguments: one compile for the
    file's re-simulations of one shape (a closure over the inertia for each call compiled the
    same program again: seven times, 2.3 s of the float64 pass)."""

    def field(t, y, u):
        return y[1], jnp.linalg.solve(inertia, u - jnp.cross(y[1], inertia @ y[1]))

    ts = jnp.linspace(0.0, time, controls.shape[0] + 1)
    return jq.solve_fixed_steps(
        jq.RKMK4(), jq.BodyRateTerm(field), ts, (q0, w0), substeps=substeps, interval_args=controls
    )


# ------------------------------------------------------------------ solve_shooting on its own


def test_solve_shooting_matches_scipy_on_a_bounded_double_integrator():
    """min sum h (u^2 + pos^2 vel^2) for x'' = u (exact discretisation of the held control),
    |u| <= 5, rest to rest over a unit distance in unit time: the bound is active (the
    unconstrained optimum peaks above 6); SLSQP on the same discrete problem is the reference.
    The state cost makes the stage Hessian depend on the point (mixed terms), and both ways of
    forming it (``hessian``) must take the same steps: the same iterates to rounding, in the same
    number of iterations (a wrong Hessian would still find the KKT point, by other steps)."""
    n, h = 10, 0.1

    def stage(x, u, p, data, k):
        pos, vel = x
        nxt = jnp.stack([pos + h * vel + 0.5 * h * h * u[0], vel + h * u[0]])
        return nxt, h * (u[0] ** 2 + pos**2 * vel**2), jnp.concatenate([u - 5.0, -u - 5.0])

    problem = jq.ShootingProblem(stage, lambda x, data: x - jnp.asarray([1.0, 0.0]), lambda p, data: jnp.zeros(()))
    x0 = jnp.zeros(2)
    solve = jax.jit(
        lambda mode: jq.solve_shooting(problem, x0, jnp.zeros((n, 2)), jnp.zeros((n, 1)), jnp.zeros(0), hessian=mode),
        static_argnums=0,
    )
    sol, rev = solve("forward"), solve("reverse")
    assert bool(sol.converged) and float(sol.kkt) < 1e-8
    assert int(rev.iterations) == int(sol.iterations)
    np.testing.assert_allclose(np.asarray(rev.u), np.asarray(sol.u), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="argument 'hessian' must be 'forward' or 'reverse'"):
        jq.solve_shooting(problem, x0, jnp.zeros((n, 2)), jnp.zeros((n, 1)), jnp.zeros(0), hessian="exact")

    def rollout(u):
        xs = [np.zeros(2)]
        for uk in u:
            x = xs[-1]
            xs.append(np.array([x[0] + h * x[1] + 0.5 * h * h * uk, x[1] + h * uk]))
        return np.array(xs)

    def final(u):
        return rollout(u)[-1]

    def cost(u):
        xs = rollout(u)[:-1]
        return h * np.sum(u**2 + xs[:, 0] ** 2 * xs[:, 1] ** 2)

    ref = minimize(
        cost,
        np.zeros(n),
        method="SLSQP",
        bounds=[(-5, 5)] * n,
        constraints={"type": "eq", "fun": lambda u: final(u) - np.array([1.0, 0.0])},
        options={"ftol": 1e-14, "maxiter": 500},
    )
    assert ref.success
    np.testing.assert_allclose(np.asarray(sol.u[:, 0]), ref.x, atol=1e-6)  # measured 2e-9
    np.testing.assert_allclose(float(sol.objective), ref.fun, rtol=1e-9)
    assert np.max(np.abs(np.asarray(sol.u))) > 5 - 1e-6  # the bound is active
    # The nodes are the rollout of the controls, and the multipliers of an active bound are positive.
    np.testing.assert_allclose(np.asarray(sol.x[-1]), final(np.asarray(sol.u[:, 0])), atol=1e-10)
    assert float(jnp.min(sol.path_multipliers)) >= 0
    # The control Jacobian dx_{k+1}/du_k is the held control's (h^2/2, h) at every stage, and
    # the objective is the cost of the returned controls.
    np.testing.assert_allclose(np.asarray(sol.control_jacobian), np.broadcast_to([[0.5 * h * h], [h]], (n, 2, 1)))
    np.testing.assert_allclose(float(sol.objective), cost(np.asarray(sol.u[:, 0])), rtol=1e-12)
    # Stopped by max_iter, every field still belongs to the returned point (the loop ends on an
    # evaluation there): its violation is the rollout's defects and terminal miss, its objective
    # that point's cost.
    early = jq.solve_shooting(
        problem, x0, jnp.zeros((n, 2)), jnp.zeros((n, 1)), jnp.zeros(0), max_iter=2, hessian="forward"
    )
    assert int(early.iterations) == 2 and not bool(early.converged)
    X, U = np.asarray(early.x), np.asarray(early.u[:, 0])
    nxt = np.stack([X[:-1, 0] + h * X[:-1, 1] + 0.5 * h * h * U, X[:-1, 1] + h * U], -1)
    expected = max(np.max(np.abs(nxt - X[1:])), np.max(np.abs(X[-1] - [1.0, 0.0])), np.max(np.abs(U)) - 5.0)
    np.testing.assert_allclose(float(early.violation), expected, rtol=1e-12)
    expected_cost = h * np.sum(U**2 + X[:-1, 0] ** 2 * X[:-1, 1] ** 2)
    np.testing.assert_allclose(float(early.objective), expected_cost, rtol=1e-12)


def test_no_trial_beyond_theta_max_is_accepted_however_far_the_objective_falls():
    """Two stages ``x_{k+1} = x_k + sinh(u_k)`` from 0 to ``x_2 = 1``, cost ``-24 u_0 + u_0^2 / 2
    + u_1^2 / 2``: from ``u = 0`` (violation theta_0 = 1) the first Newton step is about
    ``du = (12.5, -11.5)``, whose full step (a rollout of it misses by ``sinh(12.5) - sinh(11.5)``,
    8.5e4) lowers the cost. The filter starts empty, so only its bound ``theta_max = 1e4 max(1, theta_0)``
    (Waechter & Biegler sec. 2.3) stops that trial: the first iterate's 1-norm violation must stay
    below 1e4 (measured: 405, the half step; before the bound the full step was taken, 1.8e5), and
    the solve still ends at a KKT point, u = (12.0, -12.0) in 19 iterations (the stationarity
    conditions in closed form)."""
    n = 2

    def stage(x, u, p, data, k):
        cost = jnp.where(k == 0, -24.0 * u[0], 0.0) + 0.5 * u[0] ** 2
        return x + jnp.sinh(u), cost, jnp.full(1, -1.0, x.dtype)  # one inactive constraint

    problem = jq.ShootingProblem(stage, lambda x, data: x - 1.0, lambda p, data: jnp.zeros(()))
    start = (jnp.zeros(1), jnp.zeros((n, 1)), jnp.zeros((n, 1)), jnp.zeros(0))
    first = jq.solve_shooting(problem, *start, max_iter=1)
    X, U = np.asarray(first.x)[:, 0], np.asarray(first.u)[:, 0]
    theta = np.abs(X[1] - np.sinh(U[0])) + np.abs(X[2] - X[1] - np.sinh(U[1])) + np.abs(X[2] - 1.0)
    assert 1.0 < theta < 1e4, theta
    sol = jq.solve_shooting(problem, *start)
    assert bool(sol.converged)
    u = np.asarray(sol.u)[:, 0]
    # stationarity: (u_0 - 24) / cosh(u_0) = u_1 / cosh(u_1) (= -y), with sinh(u_0) + sinh(u_1) = 1
    np.testing.assert_allclose(np.sinh(u).sum(), 1.0, atol=1e-9)
    np.testing.assert_allclose((u[0] - 24.0) / np.cosh(u[0]), u[1] / np.cosh(u[1]), atol=1e-8)


def test_three_failed_line_searches_in_a_row_reset_the_nodes_to_the_rollout_of_the_controls(monkeypatch):
    """With ``theta_max = 0`` no trial is ever acceptable, so each iteration takes the shortest
    trial; after the third such iteration in a row the nodes are reset to the rollout of the
    controls from ``x_0`` (``x_{k+1} = x_k + sinh(u_k)``, evaluated here independently): no
    continuity defect is left. After two the defects of the starting nodes (0.5 and 0.2) are
    still there. The one-start three-wheel slew at 40 intervals, which stalled at ``max_iter``
    with every trial rejected before this reset, converges in 60 iterations (measured, float64;
    not run here: a configuration of its own to compile, 8 s)."""
    from jaxquat.control import interior_point

    monkeypatch.setattr(interior_point, "_THETA_MAX", 0.0)

    def stage(x, u, p, data, k):
        return x + jnp.sinh(u), 0.5 * u[0] ** 2, jnp.full(1, -1.0, x.dtype)

    problem = jq.ShootingProblem(stage, lambda x, data: x - 1.0, lambda p, data: jnp.zeros(()))
    start = (jnp.zeros(1), jnp.asarray([[0.5], [0.7]]), jnp.zeros((2, 1)), jnp.zeros(0))

    def defects(sol):
        x, u = np.asarray(sol.x)[:, 0], np.asarray(sol.u)[:, 0]
        return np.abs(x[1:] - x[:-1] - np.sinh(u))

    two, three = (jq.solve_shooting(problem, *start, max_iter=n) for n in (2, 3))
    assert int(two.iterations) == 2 and int(three.iterations) == 3
    assert np.all(defects(two) > 0.1), defects(two)
    assert np.max(defects(three)) < 1e-12, defects(three)
    assert np.max(np.abs(np.asarray(three.u))) > 0  # the shortest trials moved the controls
    # Batched (its custom_vmap rule): only the members that failed are rolled out, and none
    # when none failed.
    reset = jax.vmap(interior_point._node_reset(stage, 2), in_axes=(0, 0, 0, None, None, None))
    X = jnp.asarray([[[0.5], [0.7]], [[0.1], [0.2]]])
    U = jnp.asarray([[[0.3], [0.4]], [[-0.2], [0.1]]])
    rolled = np.cumsum(np.sinh(np.asarray(U)), axis=1)
    out = np.asarray(reset(jnp.asarray([True, False]), X, U, jnp.zeros(0), jnp.zeros(1), None))
    np.testing.assert_allclose(out[0], rolled[0], rtol=1e-12)
    np.testing.assert_array_equal(out[1], np.asarray(X[1]))
    kept = reset(jnp.asarray([False, False]), X, U, jnp.zeros(0), jnp.zeros(1), None)
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(X))
    shared = jax.vmap(interior_point._node_reset(stage, 2), in_axes=(0, 0, None, None, None, None))
    out = np.asarray(shared(jnp.asarray([False, True]), X, U[0], jnp.zeros(0), jnp.zeros(1), None))
    np.testing.assert_array_equal(out[0], np.asarray(X[0]))
    np.testing.assert_allclose(out[1], rolled[0], rtol=1e-12)  # one rollout, of the shared controls


def test_under_vmap_every_carry_of_the_solver_is_batched_from_the_start_empty_ones_too():
    """The solver's while-loop carries go in batched (``_batched_from_the_start``), so that the
    loop's batching rule traces its body once: ``vmap`` with ``out_axes=None`` refuses each leaf
    as batched, the empty ``(N, 0)`` slacks of a problem without path constraints among them
    (``jnp.where`` returned those unbatched, and the rule traced the body a second time), and the
    values are the leaves'."""
    from jaxquat.control.interior_point import _batched_from_the_start

    leaves = (jnp.ones((3, 0)), jnp.asarray(4), jnp.asarray(False), jnp.arange(6.0).reshape(3, 2))
    x = jnp.ones((2, 3, 7))
    for i, leaf in enumerate(leaves):
        with pytest.raises(ValueError, match="out_axes"):
            jax.vmap(lambda x, i=i: _batched_from_the_start(leaves, x)[i], out_axes=None)(x)
        out = jax.vmap(lambda x, i=i: _batched_from_the_start(leaves, x)[i])(x)
        np.testing.assert_array_equal(np.asarray(out), np.broadcast_to(np.asarray(leaf), (2, *leaf.shape)))


def test_the_inertia_correction_keeps_a_definite_spectrum_and_bounds_an_indefinite_one():
    """The reduced Hessian's corrected eigenvalues: a positive definite spectrum above the floor is
    kept (Newton's step, and its quadratic convergence, where the reduced Hessian is already
    right); an indefinite one gets magnitudes raised to its most negative eigenvalue's, so no
    eigendirection is stepped along with less curvature than that (hand-derived cases, then random
    spectra of fixed size)."""
    from jaxquat.control.interior_point import _corrected_eigenvalues

    fix = jax.jit(_corrected_eigenvalues)
    kept = np.array([0.3, 2.0, 1e9])
    np.testing.assert_array_equal(np.asarray(fix(jnp.asarray(kept))), kept)
    np.testing.assert_array_equal(
        np.asarray(fix(jnp.asarray([-1e-6, -0.5, 0.1, 3.0]))), [0.5, 0.5, 0.5, 3.0]
    )  # the old correction gave (1e-6, 0.5, 0.1, 3): a step 5e5 times longer along the first
    np.testing.assert_array_equal(np.asarray(fix(jnp.asarray([0.0, 1e-12, 1.0]))), [1e-8, 1e-8, 1.0])  # the floor
    rng = np.random.default_rng(0)
    ev = rng.normal(size=(200, 6)) * 10.0 ** rng.uniform(-8, 3, size=(200, 6))
    out = np.asarray(jax.vmap(fix)(jnp.asarray(ev)))
    assert np.all(out >= np.abs(ev)) and np.all(out >= 1e-8)
    worst = np.maximum(-ev.min(axis=1, keepdims=True), 0.0)
    assert np.all(out >= worst)
    definite = (ev > 1e-8).all(axis=1)
    assert 0 < definite.sum() < 200
    np.testing.assert_array_equal(out[definite], ev[definite])
    np.testing.assert_array_equal(out, np.maximum(np.abs(ev), np.maximum(1e-8, worst)))


def _spectrum_matrix(rng, ev):
    """A symmetric matrix with eigenvalues ``ev`` and random eigenvectors."""
    q, _ = np.linalg.qr(rng.normal(size=(len(ev), len(ev))))
    return (q * ev) @ q.T


def test_the_reduced_newton_step_is_the_corrected_one_by_cholesky_or_by_the_eigendecomposition():
    """``_corrected_solve`` (Cholesky where the correction changes nothing, the eigendecomposition
    elsewhere) against the corrected step formed here by NumPy's ``eigh``: well-conditioned
    definite matrices (Cholesky), one eigenvalue below the floor, indefinite ones (the
    decomposition); alone, and side by side (``vmap``) with no member, a few members (each
    decomposed on its own) and many members (the whole batch decomposed) failing the test."""
    from jaxquat.control.interior_point import _cholesky_solve, _corrected_solve

    dtype = jnp.float64 if X64 else jnp.float32
    eps = np.finfo(np.dtype(dtype)).eps
    rng = np.random.default_rng(1)
    n = 12
    definite = [np.geomspace(0.1, 100.0, n)] * 12
    tiny = [np.concatenate([[1e-12], np.geomspace(0.1, 100.0, n - 1)])] * 2
    indefinite = [np.concatenate([[-0.5], np.geomspace(0.1, 100.0, n - 1)])] * 2
    spectra = np.array(definite + tiny + indefinite)  # 16: the last four fail the test
    H = np.array([_spectrum_matrix(rng, ev) for ev in spectra])
    rhs = rng.normal(size=(16, n))

    def reference(h, r):
        ev, vec = np.linalg.eigh(h)
        floor = max(1e-8, 100 * eps * np.max(np.abs(ev)))
        fixed = np.maximum(np.abs(ev), max(floor, -min(ev.min(), 0.0)))
        return vec @ ((vec.T @ r) / fixed)

    want = np.array([reference(h, r) for h, r in zip(H, rhs)])
    Hj, rj = jnp.asarray(H, dtype), jnp.asarray(rhs, dtype)
    _, ok = jax.vmap(jax.jit(_cholesky_solve))(Hj, rj)
    np.testing.assert_array_equal(np.asarray(ok), [True] * 12 + [False] * 4)
    rtol = 1e-9 if X64 else 2e-3
    one = jax.jit(_corrected_solve)
    for i in (0, 12, 14):  # Cholesky; the floor; indefinite
        np.testing.assert_allclose(np.asarray(one(Hj[i], rj[i])), want[i], rtol=rtol, atol=rtol * np.abs(want[i]).max())
    batched = jax.jit(jax.vmap(_corrected_solve))
    for rows in (range(12), [0, 1, 2, 3, 4, 5, 6, 12], list(range(16))):  # none, 1 of 8, 4 of 16 (> 16/8) fail
        rows = np.array(rows)
        got = np.asarray(batched(Hj[rows], rj[rows]))
        np.testing.assert_allclose(got, want[rows], rtol=rtol, atol=rtol * np.abs(want[rows]).max())


def test_the_solvers_run_lapack_on_one_thread_and_restore_the_caller_s_count():
    """An eager call of a solver's program (``transcription.solver_jit``) runs with LAPACK's BLAS
    on one thread (the same iterates on any machine) and gives the caller back its own count;
    inside a caller's ``jit`` it is traced like any function."""
    import threadpoolctl

    from jaxquat.control.transcription import solver_jit

    def blas_threads():
        return max(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")

    seen = []

    def program(x):
        jax.debug.callback(lambda: seen.append(blas_threads()))
        return jnp.linalg.eigh(x)[0]

    x = jnp.diag(jnp.arange(1.0, 5.0))
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        values = solver_jit(program)(x)
        after = blas_threads()
    assert seen == [1] and before == after == 2
    np.testing.assert_allclose(np.asarray(values), [1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(np.asarray(jax.jit(lambda y: solver_jit(program)(2 * y))(x)), [2.0, 4.0, 6.0, 8.0])


def test_bilimoria_wie_at_sixty_intervals_from_one_start_converges_without_a_jam():
    """The eigenaxis start of Bilimoria & Wie's slew sits near a saddle, where the reduced Hessian
    is indefinite. With negative eigenvalues only flipped to their magnitudes, the near-zero ones
    gave near-unbounded steps that the fraction-to-the-boundary rule cut to 1e-4 to 1e-2 for
    tens of iterations: at 60 intervals from one start the solve took 184 iterations (80
    intervals: 106). Raising every corrected eigenvalue to the most negative one's magnitude: 29
    (80 intervals: 45; IPOPT 45), to the same optimum 3.2434343. The bound of 80 fails the old
    correction and leaves the new one 2.7x room."""
    qf = np.array([0.0, 1.0, 0.0, 0.0])
    r = jq.constrained_minimum_time(np.eye(3), np.ones(3), Q0, qf, intervals=60, starts=1, max_iter=80)
    assert bool(r.converged) and int(r.iterations) <= 80
    assert 3.24308 < float(r.time) < 3.2440  # measured 3.2434343 (12 intervals: 3.2647)


def test_the_solver_compiles_with_its_own_xla_options_on_the_cpu():
    """The multiple-shooting solver's ``jit`` asks XLA, on the CPU, for its older elemental
    emitters (its first call 8.4-9.0 s against 10.5-12.6 s on the three benchmark slews) on a
    jaxlib that has the option (below 0.11; 0.11.2's XLA no longer does), and to skip its
    while-loop-invariant code motion (7.35-7.69 s against 7.74-8.53 s) and to run LLVM at
    optimisation level 1 (Bilimoria-Wie's compile 5.4 s against 6.9 s) with XLA's fast-compile
    preset (its solve at 80 intervals 1.0 s against 1.3 s; ``_solver_compiler_options``).
    The suite itself runs with the emitters option set for every program (``conftest.py``), so
    the solves here cannot show the difference; this checks what the probe asks for, and that
    a program compiled with them computes what the default compile does."""
    from jaxquat.control import transcription as tr

    options = tr._solver_compiler_options()
    if jax.default_backend() != "cpu":
        assert options is None
        return
    assert options is not None
    assert options["xla_disable_hlo_passes"] == "while-loop-invariant-code-motion"
    assert options["xla_backend_optimization_level"] == 1
    try:  # the preset where this XLA knows it (jaxlib 0.10.2 does)
        jax.jit(lambda y: y, compiler_options={"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"}).lower(
            np.zeros(())
        ).compile()
        preset = True
    except Exception:
        preset = False
    assert options.get("xla_cpu_opt_preset") == ("CPU_OPT_PRESET_FAST_COMPILE" if preset else None)
    assert ("xla_cpu_use_fusion_emitters" in options) == XLA_CHOOSES_EMITTERS
    if XLA_CHOOSES_EMITTERS:
        assert options["xla_cpu_use_fusion_emitters"] is False

    def loop(x):
        return jax.lax.fori_loop(0, 5, lambda i, y: jnp.sin(y) + jnp.cos(x) * i, x)

    x = jnp.linspace(0.0, 1.0, 7)
    with_options = jax.jit(loop, compiler_options=options)(x)
    # to rounding: under JAXQUAT_TEST_XLA_DEFAULTS=1 the plain jit uses the fusion emitters
    np.testing.assert_allclose(np.asarray(with_options), np.asarray(jax.jit(loop)(x)), rtol=1e-14, atol=0)


# ------------------------------------------------------------------ minimum energy


_FIRST_CALL_LOWERED: list = []  # the programs the free_energy fixture's call lowered


@pytest.fixture(scope="module")
def free_energy():
    """Two rest-to-rest slews of the unit body in one batched call: pi/2 about (1, 2, 2)/3 and
    pi/2 about z (duration 2); the programs the call lowers are kept in ``_FIRST_CALL_LOWERED``."""
    with lowered_programs() as names:
        r = jq.minimum_energy_reorientation(np.eye(3), np.stack([Q0, Q0]), np.stack([QF, QZ]), 2.0, intervals=N)
    _FIRST_CALL_LOWERED.extend(names)
    return r


def test_a_first_solve_compiles_its_preparation_as_a_few_programs(free_energy):
    """Outside ``jit``, a solve's preparation (unit quaternions, the eigenaxis scales, the solver's
    data, the starts' keys, the starts' guess) and its results' batch shape are compiled
    programs, not one compilation per operation: the fixture's call (a first call with its
    shapes in this worker, unless an earlier test made the same) lowers at most seven programs
    (those five, the solver, the probe of the solver's compiler options; the guess a program of
    its own since session 35, so that a warm start runs the cold start's solver). Before session
    33 this call lowered 48 (58 on the suite's 12-interval minimum-time slew, 0.7-0.9 s of its
    first call's 7.6-7.8 s on this 2-core CPU)."""
    assert free_energy.converged.shape == (2,)
    assert len(_FIRST_CALL_LOWERED) <= 7, _FIRST_CALL_LOWERED


class _Guessed(Exception):
    """Raised by the spy on the solver: the preparation ran, nothing was solved."""


def test_configurations_that_differ_only_in_their_bounds_share_one_guess_program(monkeypatch):
    """The starts' guess reads neither the bounds nor the cost's terms
    (``transcription.guess_config``): a 7-interval minimum-time slew (a shape no other test
    solves) lowers the guess program once, and again with a rate bound lowers none, the same
    guess to the bit. The solver itself is not run (a spy stops each call after the guess)."""
    from jaxquat.control import optimal_control

    seen = []

    def spy(data, cfg, tol, max_iter, keys, guess, warm, batch=None):
        seen.append((cfg, jax.tree.map(np.asarray, guess)))
        raise _Guessed

    monkeypatch.setattr(optimal_control, "solve", spy)
    for bound in ({}, {"rate_bound": 0.5}):
        with lowered_programs() as names, pytest.raises(_Guessed):
            jq.minimum_time_reorientation(np.eye(3), np.ones(3), Q0, QZ, intervals=7, **bound)
        assert names.count("jit(guesses)") == (0 if bound else 1), names
    (plain, guess), (bounded, guess_bounded) = seen
    assert plain.rate_bounded != bounded.rate_bounded  # two configurations
    for a, b in zip(jax.tree.leaves(guess), jax.tree.leaves(guess_bounded)):
        np.testing.assert_array_equal(a, b)


def test_minimum_energy_batch_approaches_the_closed_form_from_above(free_energy):
    """Continuous optimum 12 theta^2 / T^3 (eigenaxis, cubic angle): the held-torque optimum lies
    above it by O(1/N^2); measured 0.36 % at N = 12."""
    r = free_energy
    assert np.all(np.asarray(r.converged)) and float(jnp.max(r.kkt_residual)) < 1e-8
    assert float(jnp.max(r.violation)) < 1e-10
    exact = 12 * THETA**2 / 2.0**3
    rel = np.asarray(r.cost) / exact - 1
    assert np.all(rel > 0) and np.all(rel < 0.01), rel
    # The optimum is the eigenaxis rotation: the torque stays along the axis.
    for k, axis in enumerate([AXIS, np.array([0.0, 0.0, 1.0])]):
        u = np.asarray(r.controls[k])
        off = u - (u @ axis)[:, None] * axis[None]
        assert np.max(np.abs(off)) < 1e-6 * np.max(np.abs(u))


def test_minimum_energy_reaches_the_target_on_a_finer_resimulation(free_energy):
    r = free_energy
    for k, qf in enumerate([QF, QZ]):
        qs, ws = _resimulate(jnp.eye(3), Q0, np.zeros(3), r.controls[k], float(r.time[k]), 40)
        # RKMK4 at 10x the solver's steps: the solver's truncation error, measured below 1e-8.
        assert np.linalg.norm(np.asarray(jq.minus(qs[-1], qf))) < 1e-6
        assert np.linalg.norm(ws[-1]) < 1e-6
        # The returned trajectory is the re-integration on the solver's own grid.
        np.testing.assert_allclose(np.asarray(r.q[k][-1]), qs[-1], atol=1e-10)


def test_a_tolerance_finer_than_the_dtype_resolves_is_refused_before_the_solver_compiles():
    """JAX computes in float32 unless float64 is enabled. A float32 solve stalls near a KKT error
    of 1e-7 (this slew, measured: 7.5e-8; a minimum-time slew 2e-5), so the default tol of 1e-9
    ran the whole budget (5-10 s, most of it compiling) and then raised ``RuntimeError`` advising
    a smaller tol. A tol below eps / 100 of the arguments' dtype (here float32 arguments, as JAX
    makes them with float64 off) is refused at the call, with the way to float64, before the
    solver compiles. The failure messages of both solvers name a dtype other than float64."""
    f32 = [np.asarray(a, np.float32) for a in (np.eye(3), Q0, QF)]
    calls = {
        "optimal reorientation: tol = 1e-09 is below what float32 resolves": lambda: jq.minimum_energy_reorientation(
            *f32, 2.0, intervals=N
        ),
        "optimal reorientation: tol = 1e-09 is below what float32": lambda: jq.minimum_time_reorientation(
            f32[0], np.ones(3, np.float32), *f32[1:], intervals=N
        ),
        "optimal reorientation: tol = 1e-19 is below what float64 resolves": lambda: jq.minimum_energy_reorientation(
            np.eye(3), Q0, QF, 2.0, intervals=N, tol=1e-19
        ),
    }
    with lowered_programs() as names:
        for message, call in calls.items():
            with pytest.raises(ValueError, match=re.escape(message) + r".*jax_enable_x64.*or pass a tol of at least"):
                call()
    assert not any("_solve" in str(n) for n in names), names
    with pytest.raises(ValueError, match=r"1.2e-09 \(a minimum-time slew: to jaxquat.constrained_minimum_time\)"):
        jq.minimum_time_reorientation(f32[0], np.ones(3, np.float32), *f32[1:], intervals=N)
    check_tolerance(1.2e-9, np.float32, "solver")  # at the floors: no error
    check_tolerance(2.3e-18, np.float64, "solver")
    assert float64_hint(np.float64) == ""
    assert "float32" in float64_hint(np.float32) and "jax_enable_x64" in float64_hint(np.float32)


SUN = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
HALF = np.deg2rad(20.0)
RATE = 0.7
TORQUE = np.array([1.2, 1.2, 1.2])


@pytest.fixture(scope="module")
def constrained_energy():
    """90 degrees about z in 3 s: the body x axis would sweep through the Sun direction at 45
    degrees; keep it 20 degrees away, with rates <= 0.7 rad/s and |u_i| <= 1.2."""
    return jq.minimum_energy_reorientation(
        np.eye(3),
        Q0,
        QZ,
        3.0,
        torque_bound=TORQUE,
        rate_bound=RATE,
        keep_out=[(np.array([1.0, 0.0, 0.0]), SUN, HALF)],
        intervals=N,
    )


def test_every_constraint_holds_on_a_ten_times_finer_resimulation(constrained_energy):
    r = constrained_energy
    assert bool(r.converged) and float(r.violation) < 1e-9
    u = np.asarray(r.controls)
    assert np.all(np.abs(u) <= TORQUE * (1 + 1e-8))
    qs, ws = _resimulate(jnp.eye(3), Q0, np.zeros(3), r.controls, float(r.time), 40)
    assert np.max(np.abs(ws)) <= RATE * (1 + 1e-4)  # between the solver's steps: measured 1e-6 over
    boresight = np.asarray(jax.vmap(lambda q: jq.rotate(q, jnp.asarray([1.0, 0.0, 0.0])))(jnp.asarray(qs)))
    angle = np.arccos(np.clip(boresight @ SUN, -1, 1))
    assert np.min(angle) >= HALF - 1e-4
    # The solver's 4 RKMK4 steps per interval against 40: their truncation error (measured 1.4e-8).
    assert np.linalg.norm(np.asarray(jq.minus(qs[-1], QZ))) < 1e-6 and np.linalg.norm(ws[-1]) < 1e-6
    # Both path constraints bind (the problem is not the unconstrained one in disguise).
    assert np.min(angle) < HALF + 1e-4
    assert np.max(np.abs(ws)) > 0.99 * RATE


def test_a_keep_in_cone_is_the_complementary_keep_out_cone_and_binds():
    """Body x kept within 110 degrees of d = (-1, -1, 3)/sqrt(11): the eigenaxis path (x from
    (1, 0, 0) to (0, 1, 0) in the xy plane) leaves the cone at its middle (115 degrees), so the
    slew must tilt x towards +z. The same set is ``x`` at least 70 degrees from ``-d``: both
    forms give the same optimum (the same configuration as the fixture above, so one compile)."""
    d = np.array([-1.0, -1.0, 3.0]) / np.sqrt(11.0)
    x = np.array([1.0, 0.0, 0.0])
    common = dict(torque_bound=TORQUE, rate_bound=RATE, intervals=N)
    inside = jq.minimum_energy_reorientation(np.eye(3), Q0, QZ, 3.0, keep_in=[(x, d, np.deg2rad(110))], **common)
    outside = jq.minimum_energy_reorientation(np.eye(3), Q0, QZ, 3.0, keep_out=[(x, -d, np.deg2rad(70))], **common)
    assert bool(inside.converged) and float(inside.violation) < 1e-9
    np.testing.assert_allclose(float(inside.cost), float(outside.cost), rtol=1e-8)
    qs, _ = _resimulate(jnp.eye(3), Q0, np.zeros(3), inside.controls, float(inside.time), 40)
    axis = np.asarray(jax.vmap(lambda q: jq.rotate(q, jnp.asarray(x)))(jnp.asarray(qs)))
    angle = np.degrees(np.arccos(np.clip(axis @ d, -1, 1)))
    assert np.max(angle) <= 110 + 1e-3  # between the solver's steps
    assert np.max(angle) > 110 - 1e-3  # it binds: the unconstrained path reaches 115 degrees
    assert np.max(axis[:, 2]) > np.sin(np.deg2rad(4))  # the detour: x tilts towards +z


def test_constraints_cost_energy(constrained_energy, free_energy):
    """The constrained slew (3 s) costs more than the unconstrained eigenaxis one would
    (12 theta^2 / T^3 at T = 3 is a lower bound for any held-torque slew)."""
    assert float(constrained_energy.cost) > 12 * (np.pi / 2) ** 2 / 27


def test_sun_avoidance_example(constrained_energy, tmp_path):
    """The example solves the fixture's problem (same configuration, so it reuses the compiled
    solver in this process) and reports the constraints on a 10x finer re-simulation."""

    text = run_example_in_process("examples/sun_avoidance.py", "--out", str(tmp_path))
    assert "converged True" in text, text
    sep = float(re.search(r"least Sun angle ([\d.]+) deg", text).group(1))
    rate = float(re.search(r"max rate ([\d.]+) rad/s", text).group(1))
    assert 20.0 - 1e-2 < sep < 20.0 + 1e-2, text  # the cone binds and holds
    assert rate <= 0.7 * (1 + 1e-4), text
    assert float(re.search(r"energy ([\d.]+)", text).group(1)) == pytest.approx(
        float(constrained_energy.cost), rel=1e-9
    )
    assert (tmp_path / "sun_avoidance.png").stat().st_size > 10_000


def test_minimum_fuel_is_bang_off_bang_about_the_eigenaxis():
    """Rest-to-rest 90 degrees about z in 3 s with |u_i| <= 1, J = I: the continuous l1 optimum
    is bang-off-bang about z with switch t1 = (T - sqrt(T^2 - 4 theta)) / 2 and fuel 2 t1 =
    1.35172; held on 12 intervals the switch falls inside one, so the discrete fuel lies above
    (measured 1.36662, 1.1 %) and only the two switch intervals hold an intermediate torque."""
    r = jq.minimum_fuel_reorientation(np.eye(3), Q0, QZ, 3.0, torque_bound=np.ones(3), intervals=N)
    assert bool(r.converged) and float(r.violation) < 1e-10
    t1 = (3.0 - np.sqrt(9.0 - 4 * np.pi / 2)) / 2
    assert 0 < float(r.cost) / (2 * t1) - 1 < 0.02
    u = np.asarray(r.controls)
    assert np.max(np.abs(u[:, :2])) < 1e-6  # no torque off the eigenaxis
    on_bound, off = np.abs(np.abs(u[:, 2]) - 1) < 1e-6, np.abs(u[:, 2]) < 1e-6
    assert np.sum(~(on_bound | off)) <= 2 and np.sum(on_bound) >= 4 and np.sum(off) >= 4
    # The cost is the fuel: sigma_i = |u_i| at the optimum up to the final barrier (measured 4e-8 relative).
    np.testing.assert_allclose(float(r.cost), np.sum(np.abs(u)) * 3.0 / N, rtol=1e-6)
    qs, ws = _resimulate(jnp.eye(3), Q0, np.zeros(3), r.controls, float(r.time), 40)
    assert np.linalg.norm(np.asarray(jq.minus(qs[-1], QZ))) < 1e-6 and np.linalg.norm(ws[-1]) < 1e-6
    with pytest.raises(ValueError, match="torque_bound"):
        jq.minimum_fuel_reorientation(np.eye(3), Q0, QZ, 3.0, torque_bound=None)


# ------------------------------------------------------------------ minimum time


@pytest.fixture(scope="module")
def bilimoria_wie():
    """Bilimoria & Wie's 180 degrees about x with J = I, |u_i| <= 1, by the interior-point path.
    With a rate bound of 100 that does not bind (the optimum peaks at 1.63 rad/s): the
    configuration of the rate-bound test below, which then reuses this compiled solver (20 s)."""
    qf = np.array([0.0, 1.0, 0.0, 0.0])
    return jq.minimum_time_reorientation(
        np.eye(3), np.ones(3), Q0, qf, intervals=N, rate_bound=100.0, method="interior_point"
    )


def test_bilimoria_wie_time_and_the_switching_function_certificate(bilimoria_wie):
    """Shorter than the eigenaxis time 2 sqrt(pi) and above the continuous optimum 3.24308
    (Bilimoria & Wie 1993); the discrete KKT conditions make every control whose switching
    function d(costate . F)/du is non-zero sit on its bound, with u = -b sign(sigma)."""
    r = bilimoria_wie
    assert isinstance(r, jq.ConstrainedReorientation)
    assert bool(r.converged) and float(r.kkt_residual) < 1e-8 and float(r.violation) < 1e-10
    assert 3.24308 < float(r.time) < 2 * np.sqrt(np.pi) * 0.95  # measured 3.2647 at 12 intervals
    sigma, u = np.asarray(r.switching), np.asarray(r.controls)
    big = np.abs(sigma) > 1e-6 * np.max(np.abs(sigma))
    assert big.mean() > 0.5
    np.testing.assert_allclose(np.abs(u[big]), 1.0, atol=1e-6)
    assert np.all(np.sign(u[big]) == -np.sign(sigma[big]))
    qs, ws = _resimulate(jnp.eye(3), Q0, np.zeros(3), r.controls, float(r.time), 40)
    # The solver's 4 RKMK4 steps per interval (h = 0.068 at rates up to 1.7) against 40: their
    # truncation error, measured 2.7e-7.
    assert np.linalg.norm(np.asarray(jq.minus(qs[-1], jnp.asarray([0.0, 1.0, 0.0, 0.0])))) < 1e-5


def test_a_rate_bound_through_the_binding_signature_costs_time(bilimoria_wie):
    qf = np.array([0.0, 1.0, 0.0, 0.0])
    r = jq.minimum_time_reorientation(np.eye(3), np.ones(3), Q0, qf, rate_bound=1.0, intervals=N)
    assert bool(r.converged) and float(r.violation) < 1e-9
    assert float(r.time) > float(bilimoria_wie.time) * 1.01  # the free optimum peaks above 1.5 rad/s
    qs, ws = _resimulate(jnp.eye(3), Q0, np.zeros(3), r.controls, float(r.time), 40)
    assert np.max(np.abs(ws)) <= 1.0 + 1e-4
    assert np.all(np.abs(np.asarray(r.controls)) <= 1 + 1e-8)


# ------------------------------------------------------------------ reaction wheels


def _wheel_resimulation(r, inertia, axes, h0, substeps):
    """The returned wheel torques held per interval and integrated with ``substeps`` RKMK4 steps
    per interval through :class:`jaxquat.ReactionWheelSpacecraft`'s own vector field (its
    ``qdot`` on the quaternion leaf), independent of the optimiser's."""
    model = jq.ReactionWheelSpacecraft(inertia, axes, lambda t, y, u: (u, jnp.zeros(3)))
    n = r.controls.shape[0]
    ts = jnp.linspace(0.0, float(r.time), n + 1)
    y0 = {"q": jnp.asarray(Q0), "w": jnp.zeros(3), "h": jnp.asarray(h0, jnp.float64)}
    import diffrax

    ys = jq.solve_fixed_steps(
        jq.RKMK4(quaternions=model.quaternions),
        diffrax.ODETerm(model),
        ts,
        y0,
        substeps=substeps,
        interval_args=r.controls,
    )
    return model, ys


@pytest.fixture(scope="module")
def wheel_bilimoria_wie():
    """Bilimoria & Wie's 180 degrees about x turned by three wheels on the body axes (J = I,
    |u_i| <= 1, wheels at rest): a momentum bound of 10 that does not bind, and one of 1.5 that
    does (1.5 converges in 3.7 s, 1.2 in 10.4 s: the slowest of the 8 starts sets the time).
    Both with a rate bound and a keep-out cone that do not bind (the body x axis, which starts and
    ends on inertial +x, kept 1 degree from -x): the configuration of examples/wheel_slew.py,
    whose test then reuses the compiled solver (20 s)."""
    qf = np.array([0.0, 1.0, 0.0, 0.0])
    idle = dict(rate_bound=100.0, keep_out=[(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), 0.0175)])
    free = jq.minimum_time_reorientation(
        np.eye(3), None, Q0, qf, intervals=N, wheels=jq.ReactionWheels(np.eye(3), 1.0, momentum_limit=10.0), **idle
    )
    bound = jq.minimum_time_reorientation(
        np.eye(3), None, Q0, qf, intervals=N, wheels=jq.ReactionWheels(np.eye(3), 1.0, momentum_limit=1.5), **idle
    )
    return free, bound


def test_wheels_at_rest_turn_the_unit_body_as_a_body_torque_would(wheel_bilimoria_wie, bilimoria_wie):
    """With the wheels at rest the total momentum J w + A h stays 0, so the gyroscopic terms vanish
    and J w' = -A u: for J = A = I the rigid body's problem with the torque -u, whose optimum is
    the same time."""
    free, _ = wheel_bilimoria_wie
    assert bool(free.converged) and float(free.violation) < 1e-9
    assert np.asarray(free.torque).shape == (N * 4 + 1, 3) and np.asarray(free.wheel_momentum).shape == (N * 4 + 1, 3)
    np.testing.assert_allclose(float(free.time), float(bilimoria_wie.time), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(free.wheel_momentum), -np.asarray(free.omega), atol=1e-9)


def test_a_wheel_momentum_bound_holds_on_a_finer_resimulation_and_costs_time(wheel_bilimoria_wie):
    free, bound = wheel_bilimoria_wie
    assert bool(bound.converged) and float(bound.violation) < 1e-9
    assert np.max(np.abs(np.asarray(free.wheel_momentum))) > 1.6  # the free optimum peaks at 1.627
    assert float(bound.time) > float(free.time) * 1.003  # measured 3.2706 against 3.2536 (+0.52 %)
    model, ys = _wheel_resimulation(bound, np.eye(3), np.eye(3), np.zeros(3), 40)
    assert np.max(np.abs(np.asarray(ys["h"]))) <= 1.5 * (1 + 1e-4)
    assert np.all(np.abs(np.asarray(bound.controls)) <= 1 + 1e-8)
    qf = jnp.asarray([0.0, 1.0, 0.0, 0.0])
    assert np.linalg.norm(np.asarray(jq.minus(ys["q"][-1], qf))) < 1e-5 and np.linalg.norm(ys["w"][-1]) < 1e-5
    # The inertial momentum R(q) (J w + A h) is conserved: 0 from rest, on both integrations.
    momentum = jax.vmap(lambda q, w, h: model.momentum({"q": q, "w": w, "h": h}))(ys["q"], ys["w"], ys["h"])
    assert np.max(np.abs(np.asarray(momentum))) < 1e-12
    returned = jax.vmap(lambda q, w, h: jq.rotate(q, w + h))(bound.q, bound.omega, bound.wheel_momentum)
    assert np.max(np.abs(np.asarray(returned))) < 1e-12


def test_four_wheels_in_a_pyramid_spend_the_least_squares_wheel_torques(free_energy):
    """Four wheels in the standard pyramid (each axis 54.7 deg from body z, A^T A = 4/3 I),
    minimum energy from rest (wheel torque bound 100: not binding). From rest the inertial
    momentum stays 0, so J w + A h = 0 and J w' = -A u: for J = I the body torque is free_energy's
    rigid-body optimum tau, spent by the wheel torques of least norm, u = -A^+ tau, at 3/4 of its
    energy (|u|^2 = tau^T (A A^T)^+ tau). Measured: torques to 9.5e-13, the ratio 0.75 to
    rounding; the redundant fourth wheel (the least-squares guess and the null space of A)."""
    tilt, azimuth = np.arccos(1 / np.sqrt(3)), np.pi / 4 + np.arange(4) * np.pi / 2
    axes = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.full(4, np.cos(tilt))], 1)
    r = jq.minimum_energy_reorientation(
        np.eye(3), np.stack([Q0, Q0]), np.stack([QF, QZ]), 2.0, intervals=N, wheels=jq.ReactionWheels(axes, 100.0)
    )
    assert np.all(np.asarray(r.converged)) and float(jnp.max(r.violation)) < 1e-10
    assert np.asarray(r.controls).shape == (2, N, 4) and np.asarray(r.wheel_momentum).shape == (2, N * 4 + 1, 4)
    np.testing.assert_allclose(np.asarray(r.cost), 0.75 * np.asarray(free_energy.cost), rtol=1e-10)
    spent = -np.einsum("ij,bkj->bki", np.linalg.pinv(axes.T), np.asarray(free_energy.controls))
    np.testing.assert_allclose(np.asarray(r.controls), spent, rtol=0, atol=1e-9)


def test_wheel_slew_example(wheel_bilimoria_wie, tmp_path):
    """The reaction-wheel star-tracker slew, least time then least fuel in 1.5 times that time
    (12 intervals: the fixture's configuration for the first), every constraint checked on a 10x
    finer re-simulation through ReactionWheelSpacecraft's vector field."""

    text = run_example_in_process("examples/wheel_slew.py", "--intervals", "12", "--out", str(tmp_path))
    assert text.count("converged True") == 2, text
    sun = [float(x) for x in re.findall(r"least Sun angle ([\d.]+) deg", text)]
    rate = [float(x) for x in re.findall(r"max rate ([\d.]+)", text)]
    momentum = [float(x) for x in re.findall(r"max wheel momentum ([\d.]+)", text)]
    torque = [float(x) for x in re.findall(r"max wheel torque ([\d.]+)", text)]
    drift = [float(x) for x in re.findall(r"inertial momentum \(0 at the start\) ([\d.e+-]+)", text)]
    assert min(sun) >= 20.0 - 1e-2 and max(rate) <= 0.15 * (1 + 1e-4), text
    assert max(momentum) <= 0.12 * (1 + 1e-4) and max(torque) <= 0.1 * (1 + 1e-8), text
    assert max(drift) < 1e-12, text
    # Least time: the rate, wheel momentum and torque limits all bind.
    assert rate[0] > 0.15 * 0.999 and momentum[0] > 0.12 * 0.999 and torque[0] > 0.1 * 0.999, text
    assert (tmp_path / "wheel_slew.png").stat().st_size > 10_000


def test_wheel_slew_notebook():
    """examples/notebooks/wheel_slew.ipynb's cells run (they assert every limit on a 10x finer
    re-simulation, and least fuel below the least-time slew's). Here and not in
    test_notebooks.py: its solves have the example test's configuration, just compiled in this
    process, and reuse it."""
    run_notebook_in_process(pathlib.Path(__file__).parent.parent / "examples" / "notebooks" / "wheel_slew.ipynb")


# ------------------------------------------------------------------ a user's model


def _damped_body(y, u, args):
    """A user's model: the torqued body with viscous damping ``-c w`` (``J w' = u - w x J w - c
    w``) carrying a payload fixed to it, and an energy meter: ``z = (p, e)``, ``p`` the payload's
    attitude (a second unit quaternion, ``p' = 1/2 p (0, w)``) and ``e' = |u|^2``. Module-level:
    each function object is a configuration of its own (one compile), and its ``args`` are data."""
    q, w, z = y
    J, J_inv, c = args
    rate = jnp.concatenate([jnp.zeros(1, w.dtype), w])
    qdot, pdot = 0.5 * jq.multiply(q, rate), 0.5 * jq.multiply(z[:4], rate)
    return qdot, J_inv @ (u - jnp.cross(w, J @ w) - c * w), jnp.concatenate([pdot, jnp.sum(u * u)[None]])


PAYLOAD0 = np.asarray(jq.from_rotvec(jnp.asarray([0.3, -0.2, 0.5])), np.float64)


def _damped(inertia, c):
    return jq.ControlledModel(
        _damped_body, 3, extra0=[*PAYLOAD0, 0.0], args=(inertia, np.linalg.inv(inertia), c), extra_quaternions=1
    )


def _held_single_axis_energy(c, theta, T, n):
    """The exact least ``h sum u_k^2`` of ``theta'' = u - c theta'`` (torque held on ``n`` equal
    intervals) from rest to ``theta`` at rest in time ``T``: the minimum-norm solution of the
    linear conditions ``sum_k G_k u_k = (theta, 0)``, ``G_k`` from SciPy's matrix exponential."""
    from scipy.linalg import expm

    h = T / n
    A = np.array([[0.0, 1.0], [0.0, -c]])
    M = expm(np.block([[A, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * h)
    G = np.hstack([np.linalg.matrix_power(M[:2, :2], n - 1 - k) @ M[:2, 2:] for k in range(n)])
    u = G.T @ np.linalg.solve(G @ G.T, np.array([theta, 0.0]))
    return h * np.sum(u**2), u


@pytest.fixture(scope="module")
def damped_energy():
    """The model for three bodies in one configuration (``args`` are data): J = I undamped (the
    built-in rigid body's problem), J = I with c = 0.5, and J = diag(1, 2, 3) undamped; each the
    free_energy fixture's two slews, carrying the payload (a second quaternion) from PAYLOAD0."""
    q0, qf = np.stack([Q0, Q0]), np.stack([QF, QZ])
    return [
        jq.minimum_energy_reorientation(np.eye(3), q0, qf, 2.0, intervals=N, model=_damped(inertia, c))
        for inertia, c in ((np.eye(3), 0.0), (np.eye(3), 0.5), (np.diag([1.0, 2.0, 3.0]), 0.0))
    ]


def test_a_user_model_of_the_rigid_body_is_the_built_in_solve(damped_energy, free_energy):
    """The undamped model is the built-in transcription's NLP (the same scales, the same guess by
    the least-squares control formula), so the same iterates: controls to 1e-10, also for an
    asymmetric body, where the gyroscopic term acts (the built-in solve reuses free_energy's
    compile); the payload, which does not act on the body, changes nothing. The energy meter
    ends at the cost."""
    undamped, _, asymmetric = damped_energy
    builtin = jq.minimum_energy_reorientation(
        np.diag([1.0, 2.0, 3.0]), np.stack([Q0, Q0]), np.stack([QF, QZ]), 2.0, intervals=N
    )
    for r, ref in ((undamped, free_energy), (asymmetric, builtin)):
        assert np.all(np.asarray(r.converged)) and float(jnp.max(r.violation)) < 1e-10
        np.testing.assert_allclose(np.asarray(r.controls), np.asarray(ref.controls), rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(r.cost), np.asarray(ref.cost), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(r.extra[:, -1, 4]), np.asarray(r.cost), rtol=1e-12)
        assert r.wheel_momentum is None and np.asarray(r.extra).shape == (2, N * 4 + 1, 5)
    # the gyroscopic term changes the asymmetric body's optimum
    assert np.max(np.abs(np.asarray(asymmetric.cost) / np.asarray(undamped.cost) - 1)) > 0.1


def test_a_model_with_a_second_quaternion_advances_it_on_the_group(damped_energy):
    """``extra_quaternions=1``: the payload's attitude ``p`` rides the body's rate, so ``p(t) = (p0
    q0*) q(t)`` exactly, and the Lie step keeps it unit, for each of the damped_energy fixture's
    bodies (the payload does not act on the body: with J = I undamped the NLP is the built-in
    rigid body's, above: controls to 1.8e-13). Measured: ``p`` to 6.7e-16 of ``(p0 q0*) q``
    and unit to 2.2e-16.
    (Until session 36 the payload was a model of its own, compiled for this test alone: 31 s of
    the float64 pass on a 2-core EPYC.)"""
    offset = jq.multiply(jnp.asarray(PAYLOAD0), jq.conjugate(jnp.asarray(Q0)))
    for r in damped_energy:
        p = np.asarray(r.extra[..., :4])
        np.testing.assert_allclose(p, np.asarray(jq.multiply(offset, r.q)), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(p, axis=-1), 1.0, rtol=0, atol=1e-12)


def test_a_redundant_final_condition_is_named_when_the_solve_fails(gimballed):
    """With its gimbal's authority at zero the gimballed payload is fixed to the body (``p = (p0
    q0*) q``, here ``p = q``), so giving its final attitude as well as ``qf`` repeats three
    terminal conditions: the Newton systems are singular and the solve fails (a pi/2 slew about
    (1, 2, 2)/3, the cone moved out of the way; measured with the default 200 iterations: not
    converged, KKT residual 2.2e9, violation 1.0e-5). The error names the entry and says to
    leave it free. The diagnosis (a Jacobian of the terminal conditions at the last iterate,
    compiled) took 5.9 s at 10 intervals by reverse mode; by forward mode 3.0 s against 5.5 s
    at 12 intervals. The gain, the targets and the cone are data: the solve runs the
    ``gimballed`` fixture's compiled solver (before session 35 this test had a model of its own,
    14.7 s of XLA on a 2-core EPYC)."""
    match = r"extra_final gives entries \[0\] .* leave them NaN \(free\)"
    with lowered_programs() as names, pytest.raises(RuntimeError, match=match):
        _gimballed_slew(0, gain=0.0, qf=QF, pf=QF, avoid=-GIMBAL_MID, max_iter=20)
    assert "jit(_solve)" not in names, names  # the fixture's solver, not one of its own


def _gimballed_payload(y, u, args):
    """A payload on a three-axis gimbal: ``u[:3]`` the body torque (``J w' = u - w x J w``),
    ``u[3:]`` the gimbal rate ``nu`` (the payload's rate relative to the body, in its own
    frame); ``z = p`` the payload's attitude, ``p' = 1/2 p (0, g* w g + nu)`` with ``g = q* p``."""
    q, w, p = y
    J, J_inv, gain = args  # gain: the gimbal's authority (0: the payload fixed to the body)
    zero = jnp.zeros(1, w.dtype)
    rate = jq.rotate(jq.conjugate(jq.multiply(jq.conjugate(q), p)), w) + gain * u[3:]
    qdot = 0.5 * jq.multiply(q, jnp.concatenate([zero, w]))
    return qdot, J_inv @ (u[:3] - jnp.cross(w, J @ w)), 0.5 * jq.multiply(p, jnp.concatenate([zero, rate]))


GIMBAL_THETA, GIMBAL_AXIS = 1.0, np.array([1.0, 2.0, 2.0]) / 3
GIMBAL_PF = np.asarray(jq.from_rotvec(jnp.asarray(GIMBAL_THETA * GIMBAL_AXIS)), np.float64)
GIMBAL_MID = np.asarray(
    jq.rotate(jq.from_rotvec(jnp.asarray(0.5 * GIMBAL_THETA * GIMBAL_AXIS)), jnp.asarray([1.0, 0.0, 0.0]))
)
GIMBAL_HALF = np.deg2rad(20.0)


def _gimballed_slew(frame, *, gain=1.0, qf=Q0, pf=GIMBAL_PF, avoid=GIMBAL_MID, **kwargs):
    """The gimballed payload turned from p0 = 1 to pf (1 rad about (1, 2, 2)/3) in T = 2, the body
    at rest at both ends; the gimbal rates bounded at 1 rad/s (twice what the geodesic needs); the
    body x axis (``frame`` 0) or the payload's (``frame`` 1) kept 20 degrees from the direction
    the payload's boresight passes through at mid-slew on its geodesic (``avoid``). One
    configuration for every solve of this model (the frame, the gimbal's ``gain``, ``qf``, ``pf``
    and ``avoid`` are data), so the suite compiles it once (16 s)."""
    model = jq.ControlledModel(
        _gimballed_payload, 6, extra0=Q0, args=(np.eye(3), np.eye(3), gain), extra_quaternions=1, extra_final=pf
    )
    bounds = np.array([10.0, 10.0, 10.0, 1.0, 1.0, 1.0])
    keep_out = [(np.eye(3)[0], avoid, GIMBAL_HALF, frame)]
    return jq.minimum_energy_reorientation(
        np.eye(3), Q0, qf, 2.0, intervals=N, torque_bound=bounds, model=model, keep_out=keep_out, **kwargs
    )


@pytest.fixture(scope="module")
def gimballed():
    """:func:`_gimballed_slew` with the cone on the body (frame 0, solved to a KKT residual of
    1e-12: see the first test below) and on the payload (frame 1, the default 1e-9)."""
    return {frame: _gimballed_slew(frame, tol=tol) for frame, tol in ((0, 1e-12), (1, 1e-9))}


def test_a_given_final_payload_attitude_is_reached_at_the_least_energy(gimballed):
    """``extra_final``: the body stays at rest (q0 = qf, w = 0 at both ends) while its gimbal turns
    the payload from p0 = 1 to pf, 1 rad about (1, 2, 2)/3, in T = 2. The least int |u|^2 over the
    six controls is the payload's geodesic at constant rate: no torque, nu = theta a / T, cost
    theta^2 / T = 0.5, exact for held controls (RKMK4 advances a constant rate exactly). Solved
    with the cone on the body (frame 0), which the body at rest never nears (27 degrees from its
    boresight against 20), and the gimbal rate bound of 1 rad/s, which the geodesic's 0.5 rad/s
    stays inside: neither binds, and the solve shares the keep-out test's compile. Solved to a
    KKT residual of 1e-12 (``tol``, traced: the same compile): at the default 1e-9 the inactive
    constraints' barrier terms left the torque at 1.3e-6. Measured (21 iterations): cost to
    2.2e-16, the torque below 1.7e-9, nu to 2.4e-12, pf reached to rounding (0.0)."""
    r = gimballed[0]
    assert bool(r.converged) and float(r.violation) < 1e-10
    np.testing.assert_allclose(float(r.cost), GIMBAL_THETA**2 / 2.0, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(r.controls)[:, :3], 0.0, atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(r.controls)[:, 3:], np.broadcast_to(GIMBAL_THETA * GIMBAL_AXIS / 2.0, (N, 3)), atol=1e-8
    )
    np.testing.assert_allclose(
        np.abs(np.asarray(jq.multiply(jq.conjugate(jnp.asarray(GIMBAL_PF)), r.extra[-1]))[0]), 1.0, atol=1e-12
    )


def test_an_independent_final_condition_is_not_named_when_the_solve_fails(gimballed):
    """The gimballed payload's final attitude is independent of ``qf`` (the gimbal turns it), so
    when that solve fails (here forced: ``max_iter=3``) the error must not call the condition
    redundant. ``max_iter`` is traced, so this reuses the fixture's compiled solver."""
    with pytest.raises(RuntimeError, match="did not converge") as failure:
        _gimballed_slew(0, max_iter=3)
    assert "extra_final" not in str(failure.value)


def _np_multiply(p, q):
    """The Hamilton product in NumPy, scalar first (an independent copy for re-simulations)."""
    return np.array([p[0] * q[0] - p[1:] @ q[1:], *(p[0] * q[1:] + q[0] * p[1:] + np.cross(p[1:], q[1:]))])


def test_a_keep_out_cone_on_the_payload_boresight_bends_its_path(gimballed):
    """A cone on an extra quaternion's axis (``keep_out``'s fourth entry, frame 1): the gimballed
    payload turns from p0 = 1 to pf, 1 rad about (1, 2, 2)/3, in T = 2 with the body at rest at
    both ends, its boresight x kept 20 degrees from the direction its geodesic passes through at
    mid-slew (27.0 degrees from the boresight at both ends). The gimbal rates are bounded at
    1 rad/s, twice what the geodesic needs (``docs/optimal-control.md``: at 10 rad/s the scaled
    controls made the cone's barrier curvature hundreds of times the cost's and the solve
    stalled). The same cone on the body (frame 0, whose boresight stays at x) costs nothing more
    than the geodesic's theta^2 / T = 0.5; on the payload the detour costs more, and SciPy's
    DOP853 through the model in NumPy, from the returned controls, keeps the boresight out of
    the cone at 10x the solver's checks (at most 1e-4 rad inside, between them) and reaches pf
    and rest. Measured: 32 iterations, cost 0.76954 (frame 0: 0.5 to 2.2e-16), the boresight at
    worst 2.2e-6 rad inside the cone between checks, pf to 1.1e-15, q to 1.3e-15, |w| 4.4e-12.
    From the plain guess (the payload left at its start) this jammed (``_model_guess``)."""
    from scipy.integrate import solve_ivp

    results = gimballed
    theta, pf, mid, half = GIMBAL_THETA, GIMBAL_PF, GIMBAL_MID, GIMBAL_HALF
    np.testing.assert_allclose(float(results[0].cost), theta**2 / 2.0, rtol=1e-9)
    r = results[1]
    assert bool(r.converged) and float(r.violation) < 1e-9
    assert float(r.cost) > 0.5 * (1 + 1e-2), float(r.cost)
    controls = np.asarray(r.controls)

    def rhs(t, y):  # the model in NumPy (J = I): q' = 1/2 q (0, w), w' = u, p' = 1/2 p (0, g* w g + nu)
        u = controls[min(int(t / (2.0 / N)), N - 1)]
        q, w, p = y[:4], y[4:7], y[7:]
        g = _np_multiply(np.array([q[0], *-q[1:]]), p)
        rate = _np_multiply(_np_multiply(np.array([g[0], *-g[1:]]), np.array([0.0, *w])), g)[1:] + u[3:]
        return np.concatenate(
            [0.5 * _np_multiply(q, np.array([0.0, *w])), u[:3], 0.5 * _np_multiply(p, np.array([0.0, *rate]))]
        )

    y = np.concatenate([Q0, np.zeros(3), Q0])
    least = np.inf
    for j in range(N):  # interval by interval: the controls jump at the nodes
        ts = np.linspace(2.0 * j / N, 2.0 * (j + 1) / N, 41)
        sol = solve_ivp(rhs, ts[[0, -1]], y, method="DOP853", rtol=1e-12, atol=1e-12, t_eval=ts)
        for p in sol.y[7:].T:
            boresight = _np_multiply(_np_multiply(p, np.array([0.0, 1.0, 0.0, 0.0])), np.array([p[0], *-p[1:]]))[1:]
            least = min(least, float(np.arccos(np.clip(boresight @ mid / (p @ p), -1, 1))))
        y = sol.y[:, -1]
    assert least > half - 1e-4, (least, half)
    np.testing.assert_allclose(abs(_np_multiply(np.array([pf[0], *-pf[1:]]), y[7:])[0]), 1.0, atol=1e-9)
    assert abs(abs(y[0]) - 1.0) < 1e-9 and np.linalg.norm(y[4:7]) < 1e-8, y[:7]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(extra0=[*PAYLOAD0, 0.0], extra_quaternions=2), "extra_quaternions must be an int k >= 0 with 4 k <= 5"),
        (dict(extra0=[*PAYLOAD0, 0.0], extra_quaternions=True), "extra_quaternions must be an int"),
        (dict(extra0=[1.0, 0.0, 0.1, 0.0, 0.0], extra_quaternions=1), "first 4 entries must be 1 unit quaternions"),
        (dict(extra0=[*PAYLOAD0, 0.0], extra_final=[1.0, 0.0]), r"extra_final must be shaped \(5,\)"),
        (dict(extra0=[*PAYLOAD0, 0.0], extra_quaternions=1, extra_final=[1.0, 0, 0, np.nan, 0]), "all four entries"),
        (dict(extra0=[*PAYLOAD0, 0.0], extra_quaternions=1, extra_final=[1.0, 0, 0, 1.0, 0]), "must be unit"),
    ],
)
def test_bad_extra_quaternions_raise_naming_the_field(kwargs, match):
    model = jq.ControlledModel(_damped_body, 3, args=(np.eye(3), np.eye(3), 0.0), **kwargs)
    with pytest.raises(ValueError, match=match):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, intervals=N, model=model)


def test_a_damped_user_model_meets_the_exact_held_torque_optimum(damped_energy):
    """With J = I and damping the optimum stays on the eigenaxis, where the motion is the linear
    theta'' = u - c theta': its held-torque optimum, exact from the matrix exponential, is the
    reference (measured: cost to 2.9e-9, from the solver's RKMK4 truncation; torque to 3.4e-9),
    above the continuous optimum d^T W(T)^-1 d by O(1/N^2). The model's own field, integrated
    by SciPy's DOP853 from the returned torque, reaches the target."""
    from scipy.integrate import solve_ivp

    r = damped_energy[1]
    assert np.all(np.asarray(r.converged)) and float(jnp.max(r.violation)) < 1e-10
    exact, u_exact = _held_single_axis_energy(0.5, THETA, 2.0, N)
    np.testing.assert_allclose(np.asarray(r.cost), exact, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(r.extra[:, -1, 4]), np.asarray(r.cost), rtol=1e-12)
    for k, axis in enumerate([AXIS, np.array([0.0, 0.0, 1.0])]):
        u = np.asarray(r.controls[k])
        np.testing.assert_allclose(u @ axis, u_exact, atol=1e-7)
        assert np.max(np.abs(u - (u @ axis)[:, None] * axis[None])) < 1e-9

        def rhs(t, y, u=u):  # the model in NumPy (J = I): q' = 1/2 q (0, w), w' = u - c w, z' = |u|^2
            uk = u[min(int(t / (2.0 / N)), N - 1)]
            w = y[4:7]
            qdot = 0.5 * _np_multiply(y[:4], np.array([0.0, *w]))
            return np.concatenate([qdot, uk - 0.5 * w, [uk @ uk]])

        y = np.concatenate([Q0, np.zeros(4)])
        for j in range(N):  # interval by interval: the torque jumps at the nodes
            y = solve_ivp(rhs, (2.0 * j / N, 2.0 * (j + 1) / N), y, method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
        target = [QF, QZ][k]
        assert np.linalg.norm(np.asarray(jq.minus(jnp.asarray(y[:4]), jnp.asarray(target)))) < 1e-7
        assert np.linalg.norm(y[4:7]) < 1e-7 and abs(y[7] - float(r.cost[k])) < 1e-7


def _gyrostat(y, u, args):
    """Reaction wheels written as a user model: ``z`` the wheel momenta, ``J w' = -A u - w x (J w +
    A h)``, ``h' = u`` (the built-in wheels' dynamics)."""
    q, w, h = y
    J, J_inv, A = args
    qdot = 0.5 * jq.multiply(q, jnp.concatenate([jnp.zeros(1, w.dtype), w]))
    return qdot, J_inv @ (-(u @ A) - jnp.cross(w, J @ w + h @ A)), u


def test_wheels_as_a_user_model_reach_the_built_in_minimum_time(wheel_bilimoria_wie):
    """Minimum time with the model's extra states bounded (|h_i| <= 1.5, binding) and the torque
    bound on its controls: from one start it reaches the built-in wheels' optimum (8 starts)
    to 1e-8, and warm-started from it, the same without binding (the free optimum's wheel
    momentum peaks at 1.627). Measured: 3.2706024 and 3.2536400. The warm start (another bound,
    which is data) runs the cold start's compiled solver: it lowers no solver program of its own
    (before session 35 it compiled one, 10.4 s of XLA on a 2-core EPYC)."""
    free, bound = wheel_bilimoria_wie
    qf = np.array([0.0, 1.0, 0.0, 0.0])
    idle = dict(rate_bound=100.0, keep_out=[(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), 0.0175)])
    r = None
    for limit, ref in ((1.5, bound), (10.0, free)):
        model = jq.ControlledModel(_gyrostat, 3, extra0=np.zeros(3), extra_bound=limit, args=(np.eye(3),) * 3)
        # the second warm-started from the first (its extra states resampled with the rest)
        with lowered_programs() as names:
            r = jq.minimum_time_reorientation(
                np.eye(3), 1.0, Q0, qf, intervals=N, starts=1, model=model, init=r, **idle
            )
        assert ("jit(_solve)" in names) == (limit == 1.5), names
        assert bool(r.converged) and float(r.violation) < 1e-9
        np.testing.assert_allclose(float(r.time), float(ref.time), rtol=1e-8)
        assert np.max(np.abs(np.asarray(r.extra))) <= limit * (1 + 1e-8)
        np.testing.assert_allclose(np.asarray(r.extra), -np.asarray(r.omega), atol=1e-9)  # J w + A h = 0
    assert np.max(np.abs(np.asarray(r.extra))) > 1.6


def _bad_field(y, u, args):
    return y[0], y[1]  # no z'


def _metered_field(y, u, args):
    return 0.5 * jq.multiply(y[0], jnp.concatenate([jnp.zeros(1, u.dtype), y[1]])), u, jnp.sum(u * u)[None]


@pytest.mark.parametrize(
    "model, kwargs, exception, match",
    [
        ((_damped_body, 3), {}, TypeError, "'model' must be a jaxquat.ControlledModel"),
        (jq.ControlledModel(3, 3), {}, TypeError, "model.field must be callable"),
        (jq.ControlledModel(_damped_body, 0), {}, ValueError, "model.controls must be an int >= 1"),
        (jq.ControlledModel(_damped_body, 3, extra0=np.zeros((1, 1))), {}, ValueError, r"model.extra0 .* \(m,\)"),
        (jq.ControlledModel(_damped_body, 3, [0.0], extra_bound=[1.0, 1.0]), {}, ValueError, r"extra_bound .* \(1,\)"),
        (jq.ControlledModel(_damped_body, 3, [2.0], extra_bound=1.0), {}, ValueError, "extra0 .* exceeds"),
        (jq.ControlledModel(_damped_body, 3, [0.0], extra_scale=0.0), {}, ValueError, "extra_scale"),
        (_damped(np.eye(3), 0.0), dict(torque_bound=np.ones(2)), ValueError, r"model's 3 controls.*\(3,\)"),
        (_damped(np.eye(3), 0.0), dict(wheels=jq.ReactionWheels(np.eye(3), 1.0)), ValueError, "either 'wheels'"),
        (jq.ControlledModel(_bad_field, 3, args=()), {}, ValueError, "model.field must return the tuple"),
        (
            jq.ControlledModel(_metered_field, 3, args=()),  # z' of one entry, z given none
            {},
            ValueError,
            r"\(0,\)\) like the state .* got .*\(1,\)\)",
        ),
    ],
)
def test_bad_models_raise_naming_the_field(model, kwargs, exception, match):
    """Checked before any solve (a field's shapes at trace time of the scales)."""
    with pytest.raises(exception, match=match):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, model=model, **kwargs)


def test_a_model_needs_the_interior_point_and_a_model_result_to_warm_start():
    with pytest.raises(ValueError, match="'model' needs method='interior_point'"):
        jq.minimum_time_reorientation(np.eye(3), 1.0, Q0, QF, model=_damped(np.eye(3), 0.0), method="single_shooting")
    n = 4
    plain = jq.ConstrainedReorientation(
        *(np.zeros(shape) for shape in [(), (n + 1,), (n + 1, 4), (n + 1, 3), (n + 1, 3), (n, 3)]),
        *(np.zeros(()) for _ in range(8)),
    )
    with pytest.raises(ValueError, match="'init' must be a result of a model with 5 extra states"):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, model=_damped(np.eye(3), 0.0), init=plain)
    with pytest.raises(ValueError, match="'init' must be a result of a model with 5 extra states"):
        two = plain._replace(extra=np.zeros((n + 1, 2)))
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, model=_damped(np.eye(3), 0.0), init=two)


# ------------------------------------------------------------------ weighted mixes


def test_time_and_energy_mix_meets_its_stationarity_condition():
    """min T + rho int |u|^2 dt, 90 degrees rest to rest, J = I, |u_i| <= 10 (not binding: the
    torque peaks near 3). With J = I the held-torque problem is invariant under t -> a t,
    u -> u / a^2 (also discretised: RKMK4 is built from h f), so the least energy in time T is
    c / T^3 and the optimal T has d/dT (T + rho c / T^3) = 0: T = 3 rho E. Checked on the
    returned torque; and the continuous c = 12 theta^2 bounds c from below."""
    rho = 0.1
    r = jq.optimal_reorientation(
        np.eye(3), Q0, QZ, time_weight=1.0, energy_weight=rho, torque_bound=10 * np.ones(3), intervals=N
    )
    assert bool(r.converged) and float(r.violation) < 1e-9
    T = float(r.time)
    u = np.asarray(r.controls)
    assert np.max(np.abs(u)) < 9  # the bound does not bind
    E = T / N * np.sum(u * u)
    np.testing.assert_allclose(3 * rho * E, T, rtol=1e-7)
    np.testing.assert_allclose(float(r.cost), T + rho * E, rtol=1e-12)
    assert E * T**3 >= 12 * (np.pi / 2) ** 2 * (1 - 1e-9)  # held torque is no better than continuous


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(duration=2.0), "time_weight.*energy_weight.*fuel_weight"),
        (dict(duration=2.0, energy_weight=-1.0), "must be finite and >= 0"),
        (dict(duration=2.0, energy_weight=np.nan), "must be finite and >= 0"),
        (dict(energy_weight=1.0), "free final time .* time_weight > 0 and a torque_bound"),
        (dict(time_weight=1.0), "free final time .* torque_bound"),
        (dict(duration=2.0, time_weight=1.0, torque_bound=np.ones(3)), "'time_weight' must be 0 with a fixed"),
        (dict(duration=2.0, fuel_weight=1.0), "'torque_bound' is required with fuel_weight"),
    ],
)
def test_mix_bad_weights_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jq.optimal_reorientation(np.eye(3), Q0, QZ, **kwargs)


# ------------------------------------------------------------------ bad input (no solve)


def _batched_result():
    """A stand-in for a batched result (only the shapes are read before any solve)."""
    n = 4
    return jq.ConstrainedReorientation(
        *(np.zeros((2,) + shape) for shape in [(), (n + 1,), (n + 1, 4), (n + 1, 3), (n + 1, 3), (n, 3)]),
        *(np.zeros(2) for _ in range(8)),
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(keep_out=[(np.ones(3), np.ones(3))]), "keep_out\\[0\\]"),
        (dict(keep_out=[(np.ones(2), np.ones(3), 0.3)]), "keep_out\\[0\\].*shaped \\(3,\\)"),
        (dict(keep_out=[(np.zeros(3), np.ones(3), 0.3)]), "keep_out\\[0\\].*non-zero"),
        (dict(keep_out=[(np.ones(3), np.ones(3), 4.0)]), "half_angle"),
        (dict(keep_in=[(np.ones(3), np.ones(3))]), "keep_in\\[0\\]"),
        (dict(keep_out=[], keep_in=[(np.ones(3), np.zeros(3), 0.3)]), "keep_in\\[0\\].*non-zero"),
        (dict(keep_out=[(np.ones(3), np.ones(3), 0.3, -1)]), "keep_out\\[0\\]: the frame must be an int >= 0"),
        (dict(keep_out=[(np.ones(3), np.ones(3), 0.3, 1.0)]), "keep_out\\[0\\]: the frame must be an int >= 0"),
        (dict(keep_out=[(np.ones(3), np.ones(3), 0.3, 1, 2)]), "keep_out\\[0\\] must be"),
        (dict(keep_in=[(np.ones(3), np.ones(3), 0.3, 1)]), r"frame must be 0 \(the body\) or 1..0"),
        (dict(rate_bound=-1.0), "rate_bound"),
        (dict(rate_bound=float("nan")), "rate_bound"),
        (dict(torque_bound=np.array([1.0, 0.0, 1.0])), "torque_bound"),
        (dict(intervals=1), "intervals"),
        (dict(starts=0), "'starts' must be an int >= 1"),
        (dict(mesh=[1.0]), "'mesh' must be a 1-D array of >= 2 positive"),
        (dict(mesh=[1.0, -1.0, 1.0]), "'mesh' must be a 1-D array of >= 2 positive"),
        (dict(mesh=np.ones((2, 2))), "'mesh' must be a 1-D array"),
        (dict(starts=2.0), "'starts' must be an int >= 1"),
        (dict(max_iter=2.5), "'max_iter' must be an int >= 0"),
        (dict(max_iter=-1), "'max_iter' must be an int >= 0"),
        (dict(init=_batched_result()), "'init' must be a single \\(unbatched\\) result"),
        (dict(omega0=[100.0, 0.0, 0.0]), r"cannot resolve .* intervals \* substeps >= \d+"),
    ],
)
def test_minimum_energy_bad_input_raises_naming_the_argument(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, **kwargs)


@pytest.mark.parametrize(
    "wheels, kwargs, match",
    [
        (jq.ReactionWheels(np.eye(3), 1.0), dict(torque_bound=np.ones(3)), "either 'torque_bound'"),
        (jq.ReactionWheels(np.eye(3)[:, :2], 1.0), {}, r"wheels.axes must be the spin axes shaped \(n, 3\)"),
        (jq.ReactionWheels(np.eye(3) * [1.0, 1.0, 0.0], 1.0), {}, "finite nonzero rows"),
        (jq.ReactionWheels(np.array([[1.0, 0, 0], [0, 1, 0], [1, 1, 0]]), 1.0), {}, "span the three body axes"),
        (jq.ReactionWheels(np.eye(3), [1.0, 1.0]), {}, r"wheels.torque_limit .* shaped \(3,\)"),
        (jq.ReactionWheels(np.eye(3), -1.0), {}, "wheels.torque_limit must be positive"),
        (jq.ReactionWheels(np.eye(3), 1.0, momentum_limit=0.0), {}, "wheels.momentum_limit must be positive"),
        (jq.ReactionWheels(np.eye(3), 1.0, momentum0=np.ones(2)), {}, r"wheels.momentum0 .* shaped \(3,\)"),
        (jq.ReactionWheels(np.eye(3), 1.0, 0.5, momentum0=np.ones(3)), {}, "exceeds wheels.momentum_limit"),
        (jq.ReactionWheels(np.eye(3), 1.0), dict(init=_batched_result()._replace(time=np.zeros(()))), "wheel_momentum"),
    ],
)
def test_bad_wheels_raise_naming_the_field(wheels, kwargs, match):
    with pytest.raises(ValueError, match=match):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, wheels=wheels, **kwargs)


def test_wheels_need_a_reaction_wheels_and_the_interior_point():
    with pytest.raises(TypeError, match="'wheels' must be a jaxquat.ReactionWheels"):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, wheels=(np.eye(3), 1.0))
    with pytest.raises(ValueError, match="'wheels' needs method='interior_point'"):
        jq.minimum_time_reorientation(
            np.eye(3), None, Q0, QF, wheels=jq.ReactionWheels(np.eye(3), 1.0), method="single_shooting"
        )


def test_refine_mesh_of_a_batched_result_raises():
    with pytest.raises(ValueError, match="'result' must be a single"):
        jq.refine_mesh(_batched_result())


def test_init_that_is_not_a_result_raises_naming_it():
    with pytest.raises(TypeError, match="'init' must be an earlier result"):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 2.0, init=np.zeros(3))


def test_bad_duration_method_and_shapes_raise():
    with pytest.raises(ValueError, match="duration"):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF, 0.0)
    with pytest.raises(ValueError, match="qf"):
        jq.minimum_energy_reorientation(np.eye(3), Q0, QF[:3], 1.0)
    with pytest.raises(ValueError, match="method"):
        jq.minimum_time_reorientation(np.eye(3), np.ones(3), Q0, QF, method="ipopt")
    with pytest.raises(ValueError, match="single_shooting"):
        jq.minimum_time_reorientation(np.eye(3), np.ones(3), Q0, QF, rate_bound=1.0, method="single_shooting")


def test_the_suite_runs_lapack_on_one_openblas_thread():
    """``conftest.py`` asks scipy's OpenBLAS, the LAPACK that jax calls on a CPU (``eigh`` and QR
    in the interior point's Newton step), for one thread: with two the one-start wheel slew took
    169 iterations, with one 177, so an iteration count or a marginal convergence would otherwise
    depend on the cores of the machine. This checks that the request reached the library jax
    loaded (it would not if something loaded scipy's OpenBLAS before the conftest ran)."""
    import ctypes

    jax.block_until_ready(jnp.linalg.eigh(jnp.eye(3)))  # jax's LAPACK is loaded
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "scipy.libs" in line and "libscipy_openblas" in line}
    except OSError:
        pytest.skip("no /proc/self/maps on this system")
    if not paths:
        pytest.skip("this scipy does not bundle OpenBLAS")
    for path in paths:
        assert ctypes.CDLL(path).scipy_openblas_get_num_threads() == 1, path
