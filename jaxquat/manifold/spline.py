"""Cubic rotation spline through timed keys, with continuous angular velocity and acceleration.

The construction is the one of scipy's ``RotationSpline`` (facts, not code):
on segment ``i`` (``t_i <= t <= t_(i+1)``, ``h = t - t_i``) the attitude is
``q_i Exp(theta(h))`` with ``theta`` a cubic in ``h``, ``theta(0) = 0`` and
``theta(dt_i) = Log(q_i* q_(i+1))``. The body angular rates ``w_i`` at the keys
are chosen so that the angular acceleration is continuous across keys, which
gives a block-tridiagonal system in the ``w_i`` with a term quadratic in the
rates; it is solved by fixed-point iteration (at most ``max_iter`` sweeps,
stopping when every rate changes by less than ``tol (1 + |w|)``, scipy's rule).
The end rates are ``Log(q_0* q_1)/dt_0`` and ``Log(q_(n-2)* q_(n-1))/dt_(n-2)``.
Rates are body-frame: ``w = J_r(theta) theta'`` and
``alpha = J_r(theta) theta'' + (d/dt J_r(theta)) theta'``.

Everything is JAX: the spline can be built inside ``jit``, ``vmap``-ed over key
sets, and differentiated with respect to the keys and the times (the fixed-point
sweeps run in a ``fori_loop`` with a fixed trip count, freezing once converged,
so reverse mode works).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation

__all__ = ["RotationSpline"]


def _nonlinear_term(theta: Array, theta_dot: Array) -> Array:
    """``(d/dt J_r(theta)) theta'``: the part of the angular acceleration quadratic in ``theta'``."""
    _, djac = jax.jvp(_rotation.right_jacobian, (theta,), (theta_dot,))
    return _arrays.matvec(djac, theta_dot)


def _thomas_factor(lower: Array, diag: Array, upper: Array):
    """Forward elimination of a block-tridiagonal matrix (3x3 blocks, ``m`` block rows)."""

    def step(c_prev, blocks):
        lo, d, up = blocks
        inv = jnp.linalg.inv(d - _arrays.matmul(lo, c_prev))
        c = _arrays.matmul(inv, up)
        return c, (c, inv)

    zero = jnp.zeros_like(diag[0])
    _, (c, inv) = jax.lax.scan(step, zero, (lower, diag, upper))
    return c, inv


def _thomas_solve(lower: Array, c: Array, inv: Array, b: Array) -> Array:
    def forward(d_prev, blocks):
        lo, iv, bb = blocks
        d = _arrays.matvec(iv, bb - _arrays.matvec(lo, d_prev))
        return d, d

    _, d = jax.lax.scan(forward, jnp.zeros_like(b[0]), (lower, inv, b))

    def backward(x_next, blocks):
        cc, dd = blocks
        x = dd - _arrays.matvec(cc, x_next)
        return x, x

    _, x = jax.lax.scan(backward, jnp.zeros_like(b[0]), (c, d), reverse=True)
    return x


def _solve_rates(dt: Array, theta: Array, max_iter: int, tol: float):
    """Key rates ``w_0..w_(n-2)`` (segment starts) and ``theta'`` at segment ends."""
    n1 = theta.shape[0]  # number of segments, n - 1 >= 2
    m = n1 - 1  # interior keys
    a = _rotation.right_jacobian_inverse(theta)  # theta' = A w
    a_inv = _rotation.right_jacobian(theta)
    rates = theta / dt[:, None]
    w_first, w_last = rates[0], rates[-1]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=theta.dtype), (m, 3, 3))
    diag = (4 * (1 / dt[:-1] + 1 / dt[1:]))[:, None, None] * eye
    zero = jnp.zeros((1, 3, 3), theta.dtype)
    lower = jnp.concatenate([zero, 2 * a_inv[1:-1] / dt[1:-1, None, None]], axis=0)
    upper = jnp.concatenate([2 * a[1:-1] / dt[1:-1, None, None], zero], axis=0)
    b0 = 6 * (theta[:-1] / dt[:-1, None] ** 2 + theta[1:] / dt[1:, None] ** 2)
    b0 = b0.at[0].add(-2 / dt[0] * _arrays.matvec(a_inv[0], w_first))
    b0 = b0.at[-1].add(-2 / dt[-1] * _arrays.matvec(a[-1], w_last))
    c, inv = _thomas_factor(lower, diag, upper)

    def sweep(_, carry):
        r, done = carry
        theta_dot = _arrays.matvec(a, r)
        b = b0 - _nonlinear_term(theta[:-1], theta_dot[:-1])
        new = _thomas_solve(lower, c, inv, b)
        converged = jnp.all(jnp.abs(new - r[:-1]) < tol * (1 + jnp.abs(new)))
        r = jnp.where(done, r, r.at[:-1].set(new))
        return r, done | converged

    rates, _ = jax.lax.fori_loop(0, max_iter, sweep, (rates, jnp.asarray(False)))
    theta_dot_end = _arrays.matvec(a, rates)
    return jnp.concatenate([w_first[None], rates[:-1]], axis=0), theta_dot_end


class RotationSpline:
    """``RotationSpline(times, quats)``: a C2 cubic rotation spline through timed keys.

    ``times`` ``(n,)`` strictly increasing, ``quats`` ``(n, 4)`` scalar first,
    ``n >= 2`` (signs of the keys do not matter). Call as ``spline(t, order=0)``
    for attitudes ``(..., 4)``, ``order=1`` for body angular velocity and
    ``order=2`` for body angular acceleration ``(..., 3)``, as scipy's
    ``RotationSpline`` defines them (agreement to 1e-10 in float64 is tested).
    ``t`` outside ``[t_0, t_(n-1)]`` extrapolates the end cubic.

    A registered pytree: pass it through ``jit``/``vmap``/``grad``; build it
    inside a transformed function to differentiate with respect to the keys and
    times. ``max_iter`` and ``tol`` control the fixed-point solve of the rates.

    Args:
        times: key times ``(n,)``, strictly increasing, ``n >= 2``.
        quats: key attitudes ``(n, 4)``, scalar first, either sign.
        max_iter: iterations of the fixed-point solve for the key rates.
        tol: its stopping tolerance on the change of the rates.
    """

    def __init__(self, times: Any, quats: Any, *, max_iter: int = 10, tol: float = 1e-9):
        quats = _checks.quat(quats, "quats")
        times = _checks.scalar_like(times, "times")
        if quats.ndim != 2 or quats.shape[0] < 2:
            raise ValueError(f"argument 'quats' must be shaped (n, 4) with n >= 2, got shape {tuple(quats.shape)}")
        if times.shape != quats.shape[:1]:
            raise ValueError(
                f"argument 'times' must be shaped (n,) with n = {quats.shape[0]} (one per key), got shape "
                f"{tuple(times.shape)}"
            )
        times, quats = _checks.arguments(times=(times, "scalars"), quats=(quats, "quaternions"))
        if not _checks.is_traced(times) and not np.all(np.diff(np.asarray(times, dtype=np.float64)) > 0):
            raise ValueError(f"argument 'times' must be strictly increasing, got {np.asarray(times).tolist()}")
        self.times = times  # the input dtype; keys and coefficients in the working dtype
        work = _checks.working_dtype(times.dtype)
        self.keys, self.coeffs = _arrays.compiled(
            _fit, times.astype(work), quats.astype(work), max_iter=max_iter, tol=tol
        )

    def __call__(self, t: Float[ArrayLike, "*shape"] | float, order: int = 0) -> Array:
        """Attitude (``order=0``, ``(..., 4)``), body angular velocity (1) or acceleration (2) at ``t``.

        Args:
            t: times of any shape.
            order: 0, 1 or 2.

        Returns:
            ``(*t.shape, 4)`` for ``order=0``, else ``(*t.shape, 3)`` in the body frame.
        """
        if order not in (0, 1, 2):
            raise ValueError(f"argument 'order' must be 0, 1 or 2, got {order!r}")
        dtype, work = self.times.dtype, self.coeffs.dtype
        t = _checks.scalar_like(t, "t").astype(dtype).astype(work)
        times = self.times.astype(work)
        return _arrays.compiled(_evaluate, times, self.keys, self.coeffs, t, order=order).astype(dtype)


# The construction and the evaluation are jitted functions (traced once per shape and dtype):
# called eagerly, the construction ran op by op and took 5.5 s for its first 5-key spline and
# 0.9 s for every further one on the reference 2-core machine; jitted, the first costs its
# compile and the next ones milliseconds (_arrays.compiled). Inside a user's jit they simply inline.
def _fit(times: Array, quats: Array, max_iter: int, tol: float) -> tuple[Array, Array]:
    """Sign-aligned keys and the cubic coefficients ``(3, n-1, 3)``: ``theta(h) = ((c0 h + c1) h + c2) h``."""
    keys = _rotation.align_signs(quats)
    dt = jnp.diff(times)
    theta = _rotation.to_rotvec(_quaternion.multiply(_quaternion.conjugate(keys[:-1]), keys[1:]))
    if theta.shape[0] == 1:
        rates, theta_dot_end = theta / dt[:, None], theta / dt[:, None]
    else:
        rates, theta_dot_end = _solve_rates(dt, theta, max_iter, tol)
    d = dt[:, None]
    coeffs = jnp.stack(
        [
            (-2 * theta + d * rates + d * theta_dot_end) / d**3,
            (3 * theta - 2 * d * rates - d * theta_dot_end) / d**2,
            rates,
        ],
        axis=0,
    )
    return keys, coeffs


def _evaluate(times: Array, keys: Array, coeffs: Array, t: Array, order: int) -> Array:
    n = times.shape[0]
    i = jnp.clip(jnp.searchsorted(times, t, side="right") - 1, 0, n - 2)
    h = (t - times[i])[..., None]
    c0, c1, c2 = coeffs[0][i], coeffs[1][i], coeffs[2][i]
    theta = ((c0 * h + c1) * h + c2) * h
    theta_dot = (3 * c0 * h + 2 * c1) * h + c2
    if order == 0:
        return _quaternion.multiply(keys[i], _rotation.from_rotvec(theta))
    jac = _rotation.right_jacobian(theta)
    if order == 1:
        return _arrays.matvec(jac, theta_dot)
    return _arrays.matvec(jac, 6 * c0 * h + 2 * c1) + _nonlinear_term(theta, theta_dot)


def _flatten(s: RotationSpline):
    return (s.times, s.keys, s.coeffs), None


def _unflatten(_, children):
    s = object.__new__(RotationSpline)
    s.times, s.keys, s.coeffs = children
    return s


jax.tree_util.register_pytree_node(RotationSpline, _flatten, _unflatten)
