"""A primal-dual interior-point method for multiple-shooting optimal control, in JAX.

The problem (a stage-structured NLP; ``x_0`` given, ``k = 0 .. N-1``)::

    minimise    phi(p) + sum_k l(x_k, u_k, p)
    subject to  x_{k+1} = F(x_k, u_k, p)            (continuity: the shooting defects)
                e(x_N) = 0                          (terminal conditions)
                g(x_k, u_k, p) <= 0                 (path constraints, any number per stage)

with node states ``x_k``, controls ``u_k`` and global parameters ``p`` (e.g. the final time)
all unknowns. ``F`` is one shooting interval (any integrator; the stages are evaluated side
by side with ``vmap``, not in sequence).

Method (Nocedal & Wright, *Numerical Optimization*, 2nd ed., ch. 19; the filter of Waechter &
Biegler, *Math. Program.* 106 (2006)): slacks ``g + s = 0, s > 0``, the barrier
``-mu sum log s``, and Newton's method on the perturbed KKT conditions with exact second
derivatives from JAX (the Hessian of each stage's Lagrangian forward over forward, or forward
over reverse for large batches, ``vmap`` over stages). Each Newton system is solved by
*condensing* (Bock & Plitt 1984): the linearised continuity
``dx_{k+1} = A_k dx_k + B_k du_k + C_k dp + d_k`` is eliminated by a forward recursion,
leaving a dense problem in ``(du, dp)`` (``N nu + np`` unknowns) with only the terminal
conditions as constraints; that one is solved by the null-space method, and the
reduced Hessian's eigenvalues are replaced by their absolute values, raised to at least
``max(1e-8, 100 eps max|eigenvalue|)`` and, where it is indefinite, to the magnitude of its most
negative eigenvalue, so every step is a descent direction of bounded length (the inertia
correction, :func:`_corrected_eigenvalues`; a strict local minimum has a positive definite reduced
Hessian, where this changes nothing and Newton converges quadratically; there the step comes from
a Cholesky factorisation and the eigenvalues are not computed, :func:`_corrected_solve`). The continuity
multipliers (the discrete costates) come from the backward recursion. Steps keep
``s, lambda > 0`` by the fraction-to-the-boundary rule and are accepted by a filter line
search on (constraint violation, barrier objective) with trial steps ``alpha 2^-j`` evaluated
side by side; no trial whose violation exceeds ``theta_max = 1e4 max(1, theta(x_0))`` is
accepted. When no trial is acceptable the shortest is taken; after three such iterations in a
row the nodes are reset to the rollout of the controls from ``x_0`` (:func:`_node_reset`: the
continuity constraints then hold exactly, as when a multiple-shooting code initialises its
nodes by integration), the slacks and path multipliers start anew from the path constraints
there, as on the first pass, and the filter is emptied: a restoration of feasibility without a
subproblem of its own (IPOPT's restoration phase minimises the violation with elastic
variables; the violation that stalled the one-start three-wheel slew at 40 intervals was the
continuity defects' and the slacks' mismatch, which the reset removes: 200 iterations without
convergence before, 60 to the optimum after). ``mu`` falls (``mu <- min(mu / 5, mu^1.5)``) each
time the barrier problem is solved to ``10 mu``.

Why written here and not taken from a library: optimistix has no constrained minimiser and
jaxopt's (unmaintained) OSQP/``BoxCDQP`` solve QPs, not NLPs; IPOPT through CasADi is the
reference (``benchmarks/optimal_control.py``) but is not differentiable, batched or JAX.
Everything is one ``lax.while_loop``, so a batch of problems solves in one compiled call
(``vmap``) and the iteration count is the same on any machine for the same rounding.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

__all__ = ["ShootingProblem", "ShootingSolution", "solve_shooting"]


class ShootingProblem(NamedTuple):
    """The functions of a multiple-shooting problem (static: hashed by identity under ``jit``).

    ``stage(x, u, p, data, k) -> (x_next, cost, ineq)``: shooting interval ``k`` (a traced
    index), its running cost (scalar) and its path constraints ``ineq <= 0`` (a fixed-size
    vector; a constraint on ``p`` alone belongs in one stage only, e.g. ``where(k == 0, c, -1)``,
    since each copy adds its own barrier term);
    ``terminal(x_N, data) -> eq`` (``eq = 0``); ``objective(p, data) -> scalar`` (``phi``)."""

    stage: Callable
    terminal: Callable
    objective: Callable


class ShootingSolution(NamedTuple):
    """``x`` ``(N+1, nx)`` (``x[0] = x_0``), ``u`` ``(N, nu)``, ``p`` ``(np,)``; ``costates``
    ``(N, nx)`` the continuity multipliers (``costates[k]`` of ``x_{k+1} = F(x_k, u_k, p)``);
    ``terminal_multipliers`` ``(ne,)``; ``path_multipliers`` ``(N, ng)`` (``>= 0``); ``objective``;
    ``violation`` the largest absolute equality residual or positive ``ineq``; ``kkt`` the
    largest unscaled KKT residual (``mu = 0``); ``iterations``; ``converged``;
    ``control_jacobian`` ``(N, nx, nu)`` ``dx_{k+1}/du_k`` (so ``costates[k] @
    control_jacobian[k]`` is the discrete switching function ``d(costates[k] . F)/du_k``). Every
    field belongs to the returned point, also when ``max_iter`` stops the solve."""

    x: Array
    u: Array
    p: Array
    costates: Array
    terminal_multipliers: Array
    path_multipliers: Array
    objective: Array
    violation: Array
    kkt: Array
    iterations: Array
    converged: Array
    control_jacobian: Array


class _State(NamedTuple):
    X: Array  # (N, nx): x_1 .. x_N
    U: Array  # (N, nu)
    p: Array  # (np,)
    s: Array  # (N, ng) slacks
    lam: Array  # (N, ng) path multipliers
    y: Array  # (N, nx) continuity multipliers
    yT: Array  # (ne,) terminal multipliers
    mu: Array
    filt: Array  # (_FILTER, 2) filter entries (theta, phi)
    theta_max: Array  # no trial with a larger constraint violation is accepted (set on the first pass)
    it: Array
    kkt: Array
    done: Array  # converged, no finite step, or max_iter reached
    converged: Array
    B: Array  # (N, nx, nu) dx_{k+1}/du_k at (X, U, p)
    objective: Array  # at (X, U, p)
    violation: Array  # at (X, U, p)
    reset: Array  # the nodes were just reset to a rollout: start the slacks and path multipliers anew
    failures: Array  # consecutive iterations without an acceptable trial


_FILTER = 32  # filter entries kept (a circular buffer; old entries are dropped)
_TRIALS = 10  # line-search trial steps alpha_max 2^-j, j < _TRIALS, evaluated side by side
_TAU_MIN = 0.99  # fraction to the boundary
_KAPPA_EPS = 10.0  # barrier problem solved when its error <= 10 mu
_GAMMA = 1e-5  # filter margins (gamma_theta = gamma_phi)
_ETA = 1e-4  # Armijo constant
_THETA_MAX = 1e4  # theta_max = _THETA_MAX max(1, theta(x_0))
_DEBUG = False  # print one line per iteration (jax.debug.print)
_FAILURES = 3  # consecutive failed line searches after which the nodes are reset to a rollout
_FEW = 8  # a batch decomposes up to 1/_FEW of its reduced Hessians on their own (_corrected_solve)
_EIG_FLOOR = 1e-8  # reduced-Hessian eigenvalues below it (or below 100 eps |H|) are raised to it


def _corrected_eigenvalues(ev: Array) -> Array:
    """The inertia correction of the reduced Hessian's eigenvalues ``ev``: ``max(|ev_i|, delta)``
    with ``delta = max(1e-8, 100 eps max|ev|, -min(ev))``. A positive definite reduced Hessian keeps
    its eigenvalues (bar the floor), so Newton's quadratic convergence near a strict local minimum
    stays; an indefinite one has each eigenvalue replaced by its magnitude and raised to at least
    the magnitude of the most negative one, so no direction is stepped along with less curvature
    than the worst negative curvature present (the spectral form of IPOPT's shift ``H + delta_w I``,
    which shifts every eigenvalue, the large barrier ones included).

    Without the ``-min(ev)`` term (session 27 and before) a near-zero negative eigenvalue gave a
    near-unbounded step along its eigenvector, which the fraction-to-the-boundary rule then cut to
    ``alpha`` of 1e-4 to 1e-2 for tens of iterations at a fixed ``mu``. One-start minimum-time
    slews of ``benchmarks/optimal_control.py`` (float64, ``OPENBLAS_NUM_THREADS=1``, interior-point
    iterations before -> after): Bilimoria-Wie 180 deg at 80 intervals 106 -> 45 (IPOPT: 45),
    Betts asyq01 at 120 intervals 47 -> 22, Bilimoria-Wie by three wheels at 80 intervals 177 -> 32;
    the same wheels turned 150 deg about x diverged (KKT residual 1e152) and now converge in 90.
    The 26 solves of ``tests/test_optimal_control.py`` (mostly 8-20 intervals): 555 -> 542
    iterations in all, with the largest changes 64 -> 47 (wheels as a built-in model), 62 -> 48
    (wheels as a user model), 29 -> 52 (a rate bound) and 37 -> 45 (the wheel-slew example); the
    same optima. Tried and not kept, on the four slews above: IPOPT's uniform shift
    ``ev + 2 |min(ev)|`` (41, 22, diverged, 36) and ``ev + 1.2 |min(ev)|`` (29, 27, diverged,
    diverged), the ``delta`` above at twice (55, 40, 107, 75) and a tenth (53, 23, 72, diverged) of
    ``|min(ev)|``, and raising only the negative eigenvalues to ``|min(ev)|`` (Bilimoria-Wie did not
    converge)."""
    dtype = ev.dtype
    floor = jnp.maximum(_EIG_FLOOR, 100 * jnp.finfo(dtype).eps * jnp.max(jnp.abs(ev), initial=1.0))
    return jnp.maximum(jnp.abs(ev), jnp.maximum(floor, -jnp.min(ev, initial=0.0)))


def _eigen_solve(H: Array, rhs: Array) -> Array:
    """``H~^-1 rhs`` with ``H~`` the symmetric ``H`` with its eigenvalues corrected
    (:func:`_corrected_eigenvalues`)."""
    ev, vec = jnp.linalg.eigh(H)
    return vec @ ((vec.T @ rhs) / _corrected_eigenvalues(ev))


def _cholesky_solve(H: Array, rhs: Array) -> tuple[Array, Array]:
    """``(H^-1 rhs, ok)`` by Cholesky, ``ok`` where the correction of
    :func:`_corrected_eigenvalues` changes nothing: ``H = L L^T`` and the least eigenvalue's lower
    bound ``1 / trace(H^-1) = 1 / |L^-1|_F^2`` exceeds ``b = max(1e-8, 100 eps |H|_inf)``, a bound
    on the correction's floor (``|H|_inf``, the largest absolute row sum, is at least the largest
    ``|eigenvalue|``). Then every eigenvalue exceeds the floor and ``H~ = H``. The test is
    conservative by up to a factor of the dimension (then the eigendecomposition decides, as
    before).

    One chain of LAPACK calls, each on the last one's result: with a second, independent
    factorisation in the same program (of ``H - b I``, the exact test) the batched solver's
    program hung on this 2-core CPU (jaxlib 0.10.2, 4 to 100 problems side by side: every XLA
    thread waiting, no work left; the same with ``jnp.linalg.solve`` or a triangular solve
    added beside the eigendecomposition, and not when the added call took its input from the
    decomposition's result)."""
    dtype = H.dtype
    bound = jnp.maximum(_EIG_FLOOR, 100 * jnp.finfo(dtype).eps * jnp.max(jnp.sum(jnp.abs(H), axis=-1), axis=-1))
    factor = jnp.linalg.cholesky(H)
    eye = jnp.broadcast_to(jnp.eye(H.shape[-1], dtype=dtype), H.shape)
    inverse = jax.scipy.linalg.solve_triangular(factor, eye, lower=True)  # L^-1
    x = jnp.einsum("...ji,...j->...i", inverse, jnp.einsum("...ij,...j->...i", inverse, rhs))
    ok = jnp.sum(inverse * inverse, axis=(-2, -1)) * bound < 1
    return x, ok & jnp.all(jnp.isfinite(x), axis=-1)


@jax.custom_batching.custom_vmap
def _corrected_solve(H: Array, rhs: Array) -> Array:
    """The Newton step of the reduced system, ``H~^-1 rhs`` (:func:`_eigen_solve`), by Cholesky
    where ``H`` is positive definite beyond the correction's floor (:func:`_cholesky_solve`: then
    ``H~ = H``, and the two differ by rounding) and by the eigendecomposition only where it is
    not (``lax.cond``: the decomposition is not computed when the factorisation passes).
    Batched (``vmap``, the problems and starts solved side by side; a ``custom_vmap`` rule, since
    ``vmap`` turns a ``lax.cond`` on a batched predicate into both branches): none is decomposed
    when every member passes, the failed ones gathered into ``ceil(B / 8)`` slots when that many
    hold them, the whole batch otherwise.

    Why: the decomposition was a large part of each iteration's cost, and a strict local
    minimum, where the iterations end, has a positive definite reduced Hessian. Measured
    (float64, this 2-core EPYC, XLA's defaults): ``eigh`` of 114, 234, 354 rows 0.79, 3.67,
    8.17 ms against 0.07, 0.20, 0.44 ms for a Cholesky factorisation; 100 problems of 114 rows
    side by side 72 ms against 4.4 ms. Solves of ``benchmarks/optimal_control.py`` (one start,
    ``OPENBLAS_NUM_THREADS=1``, best of three after the first call): Bilimoria-Wie at 80
    intervals 0.779 -> 0.653 s, Betts asyq01 at 120 0.634 -> 0.500 s (every iteration passed the
    test; the same iterations, 45 and 22, and the same times to the last digit printed, 1e-9);
    the 100 slews of 40 intervals in one call 9.52 -> 8.58 s (the same iterations, 13-28, and
    times: in 27 of its 29 iterations some of the 100 failed the test, a mean of 6, 81 of
    them indefinite and 69 with an eigenvalue below 1e-7; with the whole batch decomposed
    whenever one failed, 9.86 s)."""
    x, ok = _cholesky_solve(H, rhs)
    return jax.lax.cond(ok, lambda: x, lambda: _eigen_solve(H, rhs))


@_corrected_solve.def_vmap
def _corrected_solve_batched(axis_size: int, in_batched: list[bool], H: Array, rhs: Array) -> tuple[Array, bool]:
    H, rhs = (a if b else jnp.broadcast_to(a, (axis_size, *a.shape)) for b, a in zip(in_batched, (H, rhs)))
    x, ok = _cholesky_solve(H, rhs)
    few = -(-axis_size // _FEW)  # at most this many decomposed on their own

    def some():  # the members that need it (and others, to fill ``few`` slots)
        slots = jnp.argsort(ok, stable=True)[:few]  # the failed ones first
        fixed = jax.vmap(_eigen_solve)(H[slots], rhs[slots])
        return x.at[slots].set(jnp.where(ok[slots, None], x[slots], fixed))

    def every():
        return jnp.where(ok[:, None], x, jax.vmap(_eigen_solve)(H, rhs))

    failed = jnp.sum(~ok)
    return jax.lax.switch((failed > 0).astype(jnp.int32) + (failed > few), (lambda: x, some, every)), True


def _node_reset(stage: Callable, N: int) -> Callable:
    """``reset(failed, X, U, p, x0, data)``: the nodes ``x_1 .. x_N`` of the controls ``U`` rolled
    out from ``x0`` stage after stage where ``failed``, else ``X``. Computed only where a line search
    failed (``lax.cond``); batched (``vmap``), a ``custom_vmap`` rule rolls out the whole batch when
    any member failed and nothing otherwise (``vmap`` turns a ``cond`` on a batched predicate into
    both branches; measured on the suite's 8-start rate-bound slew with a reset after every failed
    search, this 2-core CPU: 2.16 s with the plain ``cond``, 1.96 s with this rule)."""

    def rollout(U, p, x0, data):
        def step(x, k):
            x_next = stage(x, U[k], p, data, k)[0]
            return x_next, x_next

        return jax.lax.scan(step, x0, jnp.arange(N))[1]

    @jax.custom_batching.custom_vmap
    def reset(failed, X, U, p, x0, data):
        return jax.lax.cond(failed, lambda: rollout(U, p, x0, data), lambda: X)

    @reset.def_vmap
    def _batched(axis_size, in_batched, failed, X, U, p, x0, data):
        failed_b, X_b = in_batched[:2]
        X = X if X_b else jnp.broadcast_to(X, (axis_size, *X.shape))
        failed = failed if failed_b else jnp.broadcast_to(failed, (axis_size,))
        axes = jax.tree.map(lambda b: 0 if b else None, tuple(in_batched[2:]))

        def rolled():
            if any(jax.tree.leaves(tuple(in_batched[2:]))):
                nodes = jax.vmap(rollout, in_axes=axes)(U, p, x0, data)
            else:  # the same rollout for every member (vmap needs a batched argument)
                nodes = jnp.broadcast_to(rollout(U, p, x0, data), X.shape)
            return jnp.where(failed[:, None, None], nodes, X)

        return jax.lax.cond(jnp.any(failed), rolled, lambda: X), True

    return reset


def _batched_from_the_start(tree: Any, x: Array) -> Any:
    """``tree`` unchanged, each leaf through a select on a flag formed from ``x`` whose two
    branches are the leaf itself: under ``vmap`` over ``x`` every leaf is then batched, so that
    the batching rule of the solver's while loop, given its carries batched from the start,
    traces the body once instead of again after finding the constants (iteration count, barrier
    parameter, filter, flags) batched by a first pass. Time to the first Bilimoria-Wie result
    (12 intervals, 8 starts): 22.5-23.1 s against 24.4 s, tracing 7.7-8.3 s against 9.1 s.

    ``lax.select``, not ``jnp.where``: ``jnp.where`` returns an empty operand as it is
    (unbatched), and a problem without path constraints carries two empty ``(N, 0)`` leaves
    (the slacks and their multipliers), which the rule then found batched on a second pass
    (session 73: the suite's minimum-energy slew, two problems, float64, a 2-core Intel Xeon:
    tracing 2.65-2.68 -> 2.12-2.18 s, the first call 7.74 -> 7.21 s; the same results to the
    bit)."""
    same = x.ravel()[0] == x.ravel()[0]
    return jax.tree.map(lambda a: jax.lax.select(jnp.broadcast_to(same, jnp.shape(a)), a, a), tree)


def _split(z, nx, nu):
    return z[:nx], z[nx : nx + nu], z[nx + nu :]


def solve_shooting(
    problem: ShootingProblem,
    x0: Array,
    X: Array,
    U: Array,
    p: Array,
    data: Any = None,
    *,
    tol: float = 1e-9,
    max_iter: int = 200,
    mu0: float | Array = 0.1,
    hessian: str = "forward",
) -> ShootingSolution:
    """Solve the multiple-shooting problem from the initial guess ``(X, U, p)`` (``X`` ``(N, nx)``
    the nodes ``x_1 .. x_N``; they need not satisfy continuity, which is the point of
    multiple shooting). Stops when the scaled KKT error (Waechter & Biegler eq. (5), ``mu = 0``)
    falls below ``tol`` or after ``max_iter`` iterations. Traceable: call it inside ``jit`` and
    ``vmap`` it over a batch of ``x0``/``data``.

    Args:
        problem: the stage, terminal and objective functions (:class:`ShootingProblem`).
        x0: the fixed initial state ``(nx,)``.
        X: initial guess of the nodes ``x_1 .. x_N``, ``(N, nx)``.
        U: initial guess of the controls, ``(N, nu)``, one per shooting interval.
        p: initial guess of the parameters ``(np,)`` shared by all stages (e.g. a free final time).
        data: any pytree passed to every problem function unchanged (boundary states, bounds).
        tol: the scaled KKT error at which the solve stops. Not checked against the dtype here (the
            public solvers refuse one below eps / 100): a float32 solve stalls near 1e-7 and
            returns ``converged=False`` at the default.
        max_iter: the most interior-point iterations.
        mu0: the initial barrier parameter (small for a warm start near the solution; a traced
            scalar too, as the solvers pass it, so that cold and warm starts share a program).
        hessian: how each stage Lagrangian's Hessian is formed: ``"forward"`` (forward over
            forward, the Jacobians coming with it) or ``"reverse"`` (forward over reverse).
            Measured on asyq01's body at 40 intervals, 11 variables per stage (this 2-core
            CPU): ``"forward"`` reaches a first result in 15.1 s and then solves in 0.308 s,
            ``"reverse"`` in 18.0 s and 0.161 s; 20 problems side by side (``vmap``), 28.1 s
            and 8.96 s against 24.9 s and 3.72 s. Same iterates to rounding.

    Returns:
        A :class:`ShootingSolution`: the states, controls and parameters, the multipliers
        (``costates``, ``terminal_multipliers``, ``path_multipliers``), ``objective``,
        ``violation``, ``kkt``, ``iterations`` and ``converged``.
    """
    if hessian not in ("forward", "reverse"):
        raise ValueError(f"argument 'hessian' must be 'forward' or 'reverse', got {hessian!r}")
    N, nx = X.shape
    nu = U.shape[1]
    n_p = p.shape[0]
    nV = N * nu + n_p
    dtype = X.dtype
    stage, terminal, objective = problem

    def starts(X):  # the state each stage starts from: x_0 .. x_{N-1}
        return jnp.concatenate([x0[None], X[:-1]])

    def stages(X, U, p):
        return jax.vmap(lambda x, u, k: stage(x, u, p, data, k))(starts(X), U, jnp.arange(N))

    def merit(X, s, F, cost, g, e, phi, mu):
        """Constraint violation theta (1-norm) and the barrier objective phi_mu, from the stage values."""
        theta = jnp.sum(jnp.abs(F - X)) + jnp.sum(jnp.abs(e)) + jnp.sum(jnp.abs(g + s))
        return theta, phi + jnp.sum(cost) - mu * jnp.sum(jnp.log(s))

    def measures(X, U, p, s, mu):
        """``merit`` at a trial point (the stages evaluated there)."""
        F, cost, g = stages(X, U, p)
        return merit(X, s, F, cost, g, terminal(X[-1], data), objective(p, data), mu)

    ng = jax.eval_shape(lambda: stages(X, U, p))[2].shape[1]

    def derivatives(st: _State):
        zs = jnp.concatenate([starts(st.X), st.U, jnp.broadcast_to(st.p, (N, n_p))], axis=1)

        def one(z, yk, lk, k):
            def flat(zz):
                x, u, pp = _split(zz, nx, nu)
                return stage(x, u, pp, data, k)

            def flat_and_value(zz):  # the values come out of the Jacobian's own primal pass
                out = flat(zz)
                return out, out

            if hessian == "forward":
                # Forward over forward, the Jacobians coming with it: 121 tangent pairs through
                # the stage for 11 variables, but the shortest compile (the default).
                def gradient(zz):  # of the stage Lagrangian, with the Jacobians and values as aux
                    (Fz, lz, gz), values = jax.jacfwd(flat_and_value, has_aux=True)(zz)
                    return lz + Fz.T @ yk + gz.T @ lk, (Fz, lz, gz, values)

                W, (Fz, lz, gz, (F, cost, g)) = jax.jacfwd(gradient, has_aux=True)(z)
            else:  # forward over reverse: one Hessian-vector product per variable

                def lagrangian(zz):
                    F, cost, g = flat(zz)
                    return cost + F @ yk + g @ lk

                (Fz, lz, gz), (F, cost, g) = jax.jacfwd(flat_and_value, has_aux=True)(z)
                W = jax.jacfwd(jax.grad(lagrangian))(z)
            return F, cost, g, Fz, lz, gz, W

        F, cost, g, Fz, lz, gz, W = jax.vmap(one)(zs, st.y, st.lam, jnp.arange(N))
        e = terminal(st.X[-1], data)
        E = jax.jacfwd(terminal)(st.X[-1], data)
        WT = jax.hessian(lambda xN: st.yT @ terminal(xN, data))(st.X[-1])
        phi, dphi = jax.value_and_grad(objective)(st.p, data)
        d2phi = jax.hessian(objective)(st.p, data)
        return F, cost, g, Fz, lz, gz, W, e, E, WT, phi, dphi, d2phi

    def dual_residual(st, Fz, lz, gz, E, dphi):
        """Gradient of the Lagrangian in (X, U, p)."""
        gk = lz + jnp.einsum("kiz,ki->kz", Fz, st.y) + jnp.einsum("kiz,ki->kz", gz, st.lam)
        rx = gk[:, :nx]
        rX = jnp.concatenate([rx[1:], jnp.zeros((1, nx), dtype)]) - st.y  # x_k (k >= 1) ends defect k-1
        rX = rX.at[-1].add(E.T @ st.yT)
        rU = gk[:, nx : nx + nu]
        rp = jnp.sum(gk[:, nx + nu :], axis=0) + dphi
        return rX, rU, rp

    def errors(st, F, g, e, rX, rU, rp, mu):
        """Waechter & Biegler's scaled optimality error for the barrier parameter ``mu``."""
        n_mult = N * nx + e.shape[0] + N * ng
        s_max = 100.0
        sd = (
            jnp.maximum(
                s_max, (jnp.sum(jnp.abs(st.y)) + jnp.sum(jnp.abs(st.yT)) + jnp.sum(jnp.abs(st.lam))) / max(n_mult, 1)
            )
            / s_max
        )
        sc = jnp.maximum(s_max, jnp.sum(jnp.abs(st.lam)) / max(N * ng, 1)) / s_max
        dual = jnp.maximum(jnp.max(jnp.abs(rX)), jnp.maximum(jnp.max(jnp.abs(rU)), jnp.max(jnp.abs(rp), initial=0.0)))
        primal = jnp.maximum(jnp.max(jnp.abs(F - st.X)), jnp.max(jnp.abs(e), initial=0.0))
        primal = jnp.maximum(primal, jnp.max(jnp.abs(g + st.s), initial=0.0))
        comp = jnp.max(jnp.abs(st.s * st.lam - mu), initial=0.0)
        return jnp.maximum(jnp.maximum(dual / sd, primal), comp / sc), jnp.maximum(jnp.maximum(dual, primal), comp)

    def newton(st, mu, F, g, Fz, lz, gz, W, e, E, WT, dphi, d2phi):
        A, B, C = Fz[:, :, :nx], Fz[:, :, nx : nx + nu], Fz[:, :, nx + nu :]
        d = F - st.X
        r_i = g + st.s
        sigma = st.lam / st.s
        lam_t = sigma * r_i + mu / st.s
        Wt = W + jnp.einsum("kiz,ki,kiw->kzw", gz, sigma, gz)
        q = lz + jnp.einsum("kiz,ki->kz", gz, lam_t)

        # Condensing: dx_k = M_k dV + m_k, dV = (du_0 .. du_{N-1}, dp).
        def select_u(k):
            return jax.lax.dynamic_update_slice(jnp.zeros((nu, nV), dtype), jnp.eye(nu, dtype=dtype), (0, k * nu))

        Sp = jnp.concatenate([jnp.zeros((n_p, N * nu), dtype), jnp.eye(n_p, dtype=dtype)], axis=1)

        def forward(carry, k):
            M, m = carry
            Mn = A[k] @ M + B[k] @ select_u(k) + C[k] @ Sp
            mn = A[k] @ m + d[k]
            return (Mn, mn), (M, m)

        (MN, mN), (Ms, ms) = jax.lax.scan(forward, (jnp.zeros((nx, nV), dtype), jnp.zeros(nx, dtype)), jnp.arange(N))
        Z = jnp.concatenate([Ms, jax.vmap(select_u)(jnp.arange(N)), jnp.broadcast_to(Sp, (N, n_p, nV))], axis=1)
        zeta = jnp.concatenate([ms, jnp.zeros((N, nu + n_p), dtype)], axis=1)
        WZ = jnp.einsum("kab,kbv->kav", Wt, Z)
        H = jnp.einsum("kav,kaw->vw", Z, WZ) + MN.T @ WT @ MN + Sp.T @ d2phi @ Sp
        h = jnp.einsum("kav,ka->v", Z, jnp.einsum("kab,kb->ka", Wt, zeta) + q) + MN.T @ (WT @ mN) + Sp.T @ dphi
        H = 0.5 * (H + H.T)
        AV = E @ MN
        b = -(e + E @ mN)
        ne = AV.shape[0]
        Q, R = jnp.linalg.qr(AV.T, mode="complete")
        R1 = R[:ne]
        Y, Zn = Q[:, :ne], Q[:, ne:]
        py = jax.scipy.linalg.solve_triangular(R1.T, b, lower=True)
        Hr = Zn.T @ H @ Zn
        pz = _corrected_solve(0.5 * (Hr + Hr.T), -Zn.T @ (h + H @ (Y @ py)))
        dV = Y @ py + Zn @ pz
        yT_new = -jax.scipy.linalg.solve_triangular(R1, Y.T @ (H @ dV + h), lower=False)
        dz = jnp.einsum("kav,v->ka", Z, dV) + zeta
        dXN = MN @ dV + mN
        dX = jnp.concatenate([ms[1:] + jnp.einsum("kxv,v->kx", Ms[1:], dV), dXN[None]])

        # Costates by the backward recursion of stationarity in x_k.
        gx = (jnp.einsum("kab,kb->ka", Wt, dz) + q)[:, :nx]

        def backward(yk, k):  # yk = y+_k; returns y+_{k-1} = gx_k + A_k^T y+_k
            prev = gx[k] + A[k].T @ yk
            return prev, prev

        y_last = WT @ dXN + E.T @ yT_new
        _, ys = jax.lax.scan(backward, y_last, jnp.arange(N - 1, 0, -1))
        y_new = jnp.concatenate([ys[::-1], y_last[None]]) if N > 1 else y_last[None]
        gdz = jnp.einsum("kiz,kz->ki", gz, dz)
        lam_new = lam_t + sigma * gdz
        ds = -r_i - gdz
        dU = dV[: N * nu].reshape(N, nu)
        dp = dV[N * nu :]
        slope = jnp.sum(lz * dz) + dphi @ dp - mu * jnp.sum(ds / st.s)  # d/d alpha of the barrier objective
        return dX, dU, dp, ds, lam_new - st.lam, y_new, yT_new, slope

    reset_nodes = _node_reset(stage, N)
    empty_filter = jnp.full((_FILTER, 2), jnp.inf, dtype).at[:, 1].set(-jnp.inf)

    def fraction(v, dv, tau):
        ratio = jnp.where(dv < 0, -tau * v / jnp.where(dv < 0, dv, -1.0), jnp.inf)
        return jnp.minimum(1.0, jnp.min(ratio, initial=jnp.inf))

    def body(st: _State) -> _State:
        F, cost, g, Fz, lz, gz, W, e, E, WT, phi, dphi, d2phi = derivatives(st)
        # The slacks and path multipliers start from the first evaluation (no stage evaluation
        # of its own before the loop: one copy of the stage fewer to trace and compile).
        s_start = jnp.maximum(-g, 1e-2)
        first = st.it == 0
        anew = first | st.reset
        st = st._replace(s=jnp.where(anew, s_start, st.s), lam=jnp.where(anew, st.mu / s_start, st.lam))
        rX, rU, rp = dual_residual(st, Fz, lz, gz, E, dphi)
        err0, kkt = errors(st, F, g, e, rX, rU, rp, 0.0)
        err_mu, _ = errors(st, F, g, e, rX, rU, rp, st.mu)
        lower = tol / 10
        new_mu = jnp.where(
            err_mu <= _KAPPA_EPS * st.mu, jnp.maximum(lower, jnp.minimum(0.2 * st.mu, st.mu**1.5)), st.mu
        )
        filt = jnp.where(new_mu < st.mu, empty_filter, st.filt)
        mu = new_mu
        dX, dU, dp, ds, dlam, y_new, yT_new, slope = newton(st, mu, F, g, Fz, lz, gz, W, e, E, WT, dphi, d2phi)
        tau = jnp.maximum(_TAU_MIN, 1.0 - mu)
        a_max = fraction(st.s, ds, tau)
        a_dual = fraction(st.lam, dlam, tau)
        theta0, phi0 = merit(st.X, st.s, F, cost, g, e, phi, mu)  # the current point: no second evaluation
        # The filter's upper bound on the violation, theta_max = 1e4 max(1, theta(x_0)) (Waechter &
        # Biegler sec. 2.3: the filter starts as {theta >= theta_max}). Without it a trial whose
        # barrier objective fell was accepted however far it left the constraints: the one-start
        # three-wheel slew at 40 intervals went from theta = 11.4 to 4.0e24 in one step (objective
        # 4.13 -> 3.79) and on to NaN.
        theta_max = jnp.where(first, _THETA_MAX * jnp.maximum(1.0, theta0), st.theta_max)
        alphas = a_max * 0.5 ** jnp.arange(_TRIALS, dtype=dtype)
        thetas, phis = jax.vmap(lambda a: measures(st.X + a * dX, st.U + a * dU, st.p + a * dp, st.s + a * ds, mu))(
            alphas
        )
        theta_min = 1e-4 * jnp.maximum(1.0, theta0)
        switching = (theta0 <= theta_min) & (slope < 0) & (alphas * (-slope) ** 2.3 > theta0**1.1)
        armijo = phis <= phi0 + _ETA * alphas * slope
        sufficient = (thetas <= (1 - _GAMMA) * theta0) | (phis <= phi0 - _GAMMA * theta0)
        in_filter = jnp.all((thetas[:, None] < filt[None, :, 0]) | (phis[:, None] < filt[None, :, 1]), axis=1)
        finite = jnp.isfinite(thetas) & jnp.isfinite(phis)
        ok = finite & (thetas < theta_max) & in_filter & jnp.where(switching, armijo, sufficient)
        j = jnp.where(jnp.any(ok), jnp.argmax(ok), _TRIALS - 1)
        a = alphas[j]
        f_type = switching[j] & armijo[j]
        entry = jnp.stack([(1 - _GAMMA) * theta0, phi0 - _GAMMA * theta0])
        filt = jnp.where(f_type, filt, jnp.roll(filt, 1, axis=0).at[0].set(entry))
        s = jnp.maximum(st.s + a * ds, jnp.finfo(dtype).tiny)
        lam = st.lam + a_dual * dlam
        # Keep the multipliers within a factor 1e10 of mu / s (Waechter & Biegler eq. (16)).
        lam = jnp.clip(lam, mu / (1e10 * s), 1e10 * mu / s)
        # No acceptable trial: the shortest is taken; after _FAILURES in a row the nodes are reset
        # to the rollout of its controls from x_0 (no defects left), the slacks and path
        # multipliers started anew at the next pass and the filter emptied (the module docstring).
        # A reset after every failed search cost the suite's 8-start rate-bound slew 56 -> 88
        # iterations (1.34 -> 2.16 s), where the shortest step alone had recovered.
        U_new, p_new, X_step = st.U + a * dU, st.p + a * dp, st.X + a * dX
        failures = jnp.where(jnp.any(ok), 0, st.failures + 1)
        X_roll = reset_nodes(failures >= _FAILURES, X_step, U_new, p_new, x0, data)
        reset = (failures >= _FAILURES) & jnp.all(jnp.isfinite(X_roll))  # a rollout that overflows is not taken
        X_new = jnp.where(reset, X_roll, X_step)
        filt = jnp.where(reset, empty_filter, filt)
        step_ok = jnp.isfinite(a) & jnp.all(jnp.isfinite(dX)) & jnp.all(jnp.isfinite(dU))
        converged = err0 <= tol
        violation = jnp.maximum(
            jnp.maximum(jnp.max(jnp.abs(F - st.X)), jnp.max(jnp.abs(e), initial=0.0)), jnp.max(g, initial=0.0)
        )
        if _DEBUG:
            jax.debug.print(
                "it {i} mu {m:.1e} err0 {e:.2e} errmu {em:.2e} theta {t:.2e} phi {f:.6e} a {a:.2e} amax "
                "{am:.2e} j {j} slope {sl:.2e} sw {sw}",
                i=st.it,
                m=mu,
                e=err0,
                em=err_mu,
                t=theta0,
                f=phi0,
                a=a,
                am=a_max,
                j=j,
                sl=slope,
                sw=switching[j],
            )
        new = _State(
            X_new,
            U_new,
            p_new,
            s,
            lam,
            st.y + a * (y_new - st.y),
            st.yT + a * (yT_new - st.yT),
            mu,
            filt,
            theta_max,
            st.it + 1,
            kkt,
            jnp.asarray(False),
            converged,
            st.B,
            st.objective,
            st.violation,
            reset,
            jnp.where(reset, 0, failures),
        )
        # The iterate stays, with the values and the control Jacobian evaluated at it: the loop
        # ends in this branch (also at max_iter, one evaluation without a step), so the result
        # never needs a stage evaluation of its own after the loop.
        stop = st._replace(
            kkt=kkt,
            done=jnp.asarray(True),
            converged=converged,
            B=Fz[:, :, nx : nx + nu],
            objective=phi + jnp.sum(cost),
            violation=violation,
        )
        return jax.tree.map(lambda n, o: jnp.where(converged | ~step_ok | (st.it >= max_iter), o, n), new, stop)

    mu_start = jnp.asarray(mu0, dtype)
    ne = jax.eval_shape(lambda: terminal(X[-1], data)).shape[0]
    placeholder = jnp.ones((N, ng), dtype)  # the slacks and path multipliers, set on the first pass
    st = _State(
        X,
        U,
        p,
        placeholder,
        placeholder,
        jnp.zeros((N, nx), dtype),
        jnp.zeros(ne, dtype),
        mu_start,
        empty_filter,
        jnp.asarray(jnp.inf, dtype),
        jnp.asarray(0),
        jnp.asarray(jnp.inf, dtype),
        jnp.asarray(False),
        jnp.asarray(False),
        jnp.zeros((N, nx, nu), dtype),
        jnp.asarray(jnp.nan, dtype),
        jnp.asarray(jnp.nan, dtype),
        jnp.asarray(False),
        jnp.asarray(0),
    )
    st = _batched_from_the_start(st, X)
    st = jax.lax.while_loop(lambda st: ~st.done, body, st)
    return ShootingSolution(
        jnp.concatenate([x0[None], st.X]),
        st.U,
        st.p,
        st.y,
        st.yT,
        st.lam,
        st.objective,
        st.violation,
        st.kkt,
        st.it,
        st.converged,
        st.B,
    )
