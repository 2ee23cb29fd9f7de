"""The multiplicative extended Kalman filter (MEKF) for attitude and gyro bias.

Markley & Crassidis (2014), chapter 6, and Crassidis & Junkins (2012), Table 7.1, in this
library's conventions: ``q`` rotates body vectors into the reference frame (``r = R(q) b``),
and the attitude error is the body-frame rotation vector ``dtheta`` with
``q_true = q Exp(dtheta)`` (:func:`jaxquat.plus`). The filter state is ``(q, bias)`` and the
covariance ``P`` (6x6) is that of ``x = (dtheta, dbias)``, ``dbias = bias_true - bias``.

Models (continuous time):

* gyro: ``omega_meas = omega_true + bias + eta_v``, ``bias' = eta_u``, white ``eta_v``, ``eta_u``
  with spectral densities ``gyro_noise^2`` (angle random walk, rad/s^(1/2)) and
  ``bias_noise^2`` (rate random walk, rad/s^(3/2));
* vector sensor ``i`` (star tracker, sun sensor, magnetometer, ...): ``b_i = R(q)^T r_i + v_i``,
  ``v_i ~ N(0, vector_noise_i^2 I)`` (radians for unit vectors);
* quaternion sensor (a star tracker's attitude output): ``q_meas = q Exp(v)``,
  ``v ~ N(0, noise^2 I)``.

Propagation over ``dt`` holds the bias-corrected rate ``w = omega_meas - bias`` constant (the
sample's zero-order hold) and is exact for it: ``q <- q Exp(w dt)``, with the error-state
transition ``Phi = [[R(w dt)^T, -dt J_r(w dt)], [0, I]]`` (Markley & Crassidis' closed
forms, written with :func:`jaxquat.right_jacobian`) and the discrete
noise ``Q = [[(s_v^2 dt + s_u^2 dt^3/3) I, -(s_u^2 dt^2/2) I], [-(s_u^2 dt^2/2) I, s_u^2 dt I]]``.
Updates use the Joseph form and the exact multiplicative reset ``q <- q Exp(dtheta)``.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation

__all__ = [
    "FilterState",
    "FilterUpdate",
    "FilterResult",
    "mekf_init",
    "mekf_predict",
    "mekf_update",
    "mekf_update_quaternion",
    "mekf",
]

_LOG_2PI = float(np.log(2.0 * np.pi))


class FilterState(NamedTuple):
    """The filter's estimate: attitude ``q`` (unit), gyro ``bias`` (rad/s), error covariance ``P``."""

    q: Float[Array, "*batch 4"]
    bias: Float[Array, "*batch 3"]
    P: Float[Array, "*batch 6 6"]


class FilterUpdate(NamedTuple):
    """What a measurement update saw: the innovations (zero where a measurement is missing), the
    normalised innovation squared ``nis = nu^T S^-1 nu``, its degrees of freedom ``dof`` (3 per
    vector used) and the innovations' Gaussian log-likelihood ``-(nis + log det S + dof log 2 pi)/2``."""

    innovation: Float[Array, "*batch m 3"]
    nis: Float[Array, "*batch"]
    dof: Float[Array, "*batch"]
    log_likelihood: Float[Array, "*batch"]


class FilterResult(NamedTuple):
    """A whole run of :func:`mekf`: row ``k`` is the estimate at ``t_k = t_0 + k dt`` after the
    update with the measurements of ``t_k``, and that update's statistics (:class:`FilterUpdate`)."""

    q: Float[Array, "*batch n 4"]
    bias: Float[Array, "*batch n 3"]
    P: Float[Array, "*batch n 6 6"]
    innovation: Float[Array, "*batch n m 3"]
    nis: Float[Array, "*batch n"]
    dof: Float[Array, "*batch n"]
    log_likelihood: Float[Array, "*batch n"]


# ------------------------------------------------------------------ kernels (one filter)


def symmetric(p: Array) -> Array:
    return 0.5 * (p + jnp.swapaxes(p, -1, -2))


def _predict(q, bias, p, gyro, dt, gyro_noise, bias_noise):
    phi = (gyro - bias) * dt
    step = _rotation.from_rotvec(phi)
    q = _quaternion.multiply(q, step)
    eye = jnp.eye(3, dtype=p.dtype)
    top = jnp.concatenate([_rotation.to_matrix(step).T, -dt * _rotation.right_jacobian(phi)], axis=-1)
    bottom = jnp.concatenate([jnp.zeros_like(eye), eye], axis=-1)
    transition = jnp.concatenate([top, bottom], axis=-2)
    propagated = _arrays.matmul(_arrays.matmul(transition, p), transition.T)
    p = symmetric(propagated + process_noise(dt, gyro_noise, bias_noise, p.dtype))
    return q, bias, p


def process_noise(dt, gyro_noise, bias_noise, dtype):
    """The discrete process noise ``Q`` of (dtheta, dbias) over ``dt`` (module docstring)."""
    eye = jnp.eye(3, dtype=dtype)
    sv2, su2 = gyro_noise * gyro_noise, bias_noise * bias_noise
    q11 = (sv2 * dt + su2 * dt**3 / 3.0) * eye
    q12 = (-0.5 * su2 * dt * dt) * eye
    return jnp.block([[q11, q12], [q12, (su2 * dt) * eye]])


def innovate(q, bias, s, cross_t, residual):
    """The gain ``K = C S^-1`` from the innovation covariance ``S`` (k, k) and the error state's
    cross covariance with the measurements, transposed (``cross_t = C^T``, (k, 6)); the state reset
    by ``dx = K residual`` (``q Exp(dtheta)``, ``bias + dbias``); the NIS and ``log det S``. One
    Cholesky factor of ``S`` serves all (the MEKF's and the unscented filter's updates)."""
    chol = jnp.linalg.cholesky(s)
    solve = functools.partial(jax.scipy.linalg.cho_solve, (chol, True))
    gain = solve(cross_t).T
    dx = _arrays.matmul(gain, residual)
    nis = _arrays.matmul(residual, solve(residual))
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
    return gain, _quaternion.multiply(q, _rotation.from_rotvec(dx[:3])), bias + dx[3:], nis, logdet


def _kalman(q, bias, p, h, residual, r_diag):
    """One linear update of the error state with stacked rows ``h`` (k, 6), ``residual`` (k,) and
    diagonal measurement covariance ``r_diag`` (k,). Missing rows: ``h = 0``, ``residual = 0``,
    ``r_diag = 1`` (they then change nothing and add nothing to the statistics)."""
    mm = _arrays.matmul
    hp = mm(h, p)
    s = symmetric(mm(hp, h.T) + jnp.diag(r_diag))
    gain, q, bias, nis, logdet = innovate(q, bias, s, hp, residual)  # K = P H^T S^-1 (P symmetric)
    a = jnp.eye(6, dtype=p.dtype) - mm(gain, h)
    p = symmetric(mm(mm(a, p), a.T) + mm(gain * r_diag[None, :], gain.T))
    return (q, bias, p), nis, logdet


def quaternion_innovation(q, q_meas):
    """Whether ``q_meas`` is a measurement (no NaN), and ``Log(q* q_meas)`` (0 when it is not; the
    NaN is replaced before any arithmetic, so none reaches a gradient)."""
    valid = jnp.all(jnp.isfinite(q_meas))
    q_meas = jnp.where(valid, q_meas, q)
    return valid, jnp.where(valid, _rotation.to_rotvec(_quaternion.multiply(_quaternion.conjugate(q), q_meas)), 0.0)


def masked(body, ref):
    """Which of the ``m`` rows hold a measurement (no NaN in either vector), and both sets with
    the missing rows zeroed before any arithmetic, so no NaN reaches a gradient through ``where``."""
    valid = jnp.all(jnp.isfinite(body), axis=-1) & jnp.all(jnp.isfinite(ref), axis=-1)
    return valid, jnp.where(valid[:, None], body, 0.0), jnp.where(valid[:, None], ref, 0.0)


def statistics(nis, logdet, valid):
    """Degrees of freedom (3 per vector used) and the innovations' Gaussian log-likelihood."""
    dof = 3.0 * jnp.sum(valid).astype(nis.dtype)
    return dof, -0.5 * (nis + logdet + dof * _LOG_2PI)


def _update_vectors(q, bias, p, body, ref, sigma):
    valid, body, ref = masked(body, ref)
    predicted = _quaternion.rotate(jnp.broadcast_to(_quaternion.conjugate(q), ref.shape[:-1] + (4,)), ref)
    residual = jnp.where(valid[:, None], body - predicted, 0.0)
    m = body.shape[0]
    h_att = _arrays.hat(predicted) * valid[:, None, None]  # (m, 3, 3): d b / d dtheta = [b_hat x]
    h = jnp.concatenate([h_att, jnp.zeros_like(h_att)], axis=-1).reshape(3 * m, 6)
    r_diag = jnp.repeat(jnp.where(valid, sigma * sigma, 1.0), 3)
    (q, bias, p), nis, logdet = _kalman(q, bias, p, h, residual.reshape(-1), r_diag)
    return (q, bias, p), (residual, nis, *statistics(nis, logdet, valid))


def _update_quaternion(q, bias, p, q_meas, sigma):
    valid, residual = quaternion_innovation(q, q_meas)
    h = jnp.concatenate([jnp.eye(3, dtype=p.dtype), jnp.zeros((3, 3), p.dtype)], axis=-1) * valid
    r_diag = jnp.full((3,), jnp.where(valid, sigma * sigma, 1.0))
    (q, bias, p), nis, logdet = _kalman(q, bias, p, h, residual, r_diag)
    return (q, bias, p), (residual[None], nis, *statistics(nis, logdet, valid))


def vectorized(kernel, signature: str, options: tuple, *args) -> tuple[Array, ...]:
    """``kernel(*args, **dict(options))`` for one filter, broadcast over the batch by
    ``jnp.vectorize`` (which maps over flat outputs only, so the kernel's output, flat or
    ``(state, statistics)``, is flattened to its leaves), compiled as one program per kernel, option and shape.
    Eager calls used to run operation by operation: ``tests/test_ukf.py``'s test of eager
    init/predict/update steps compiled 266 single operations and took 12.8 s (float32, this
    2-core CPU), now 8.9 s (``_arrays.compiled``); inside a user's ``jit`` this simply inlines."""
    return _arrays.compiled(_vectorized, *args, kernel=kernel, signature=signature, options=options)


def _vectorized(*args, kernel, signature: str, options: tuple) -> tuple[Array, ...]:
    def flat(*a):
        return tuple(jax.tree.leaves(kernel(*a, **dict(options))))

    return jnp.vectorize(flat, signature=signature)(*args)


def apply_update(update, signature: str, args, options: tuple = ()) -> tuple[FilterState, FilterUpdate]:
    """A single-filter update kernel over the batch (:func:`vectorized`), its result as
    ``(FilterState, FilterUpdate)``."""
    q, bias, p, *stats = vectorized(update, signature, options, *args)
    return FilterState(q, bias, p), FilterUpdate(*stats)


def scan(predict, update, q0, bias0, p0, dt, gyro, body, ref, sigma, gyro_noise, bias_noise):
    """One filter over a record: ``predict(q, bias, P, gyro, dt, gyro_noise, bias_noise)`` and
    ``update(q, bias, P, body, ref, sigma)`` kernels in a ``lax.scan``."""
    # Step k propagates from t_{k-1} with gyro[k-1], then updates with the vectors of t_k; step 0
    # propagates over dt = 0 (the identity: Exp(0) = 1, Phi = I, Q = 0), so one scan body serves all.
    gyro_prev = jnp.concatenate([gyro[:1], gyro[:-1]], axis=0)
    dts = jnp.concatenate([jnp.zeros((1,), gyro.dtype), jnp.full((gyro.shape[0] - 1,), dt, gyro.dtype)])

    def step(state, inputs):
        g, h, b, r = inputs
        state = predict(*state, g, h, gyro_noise, bias_noise)
        state, stats = update(*state, b, r, sigma)
        return state, (*state, *stats)

    _, out = jax.lax.scan(step, (q0, bias0, p0), (gyro_prev, dts, body, ref))
    return out


RECORD_SIGNATURE = "(4),(3),(6,6),(),(n,3),(n,m,3),(n,m,3),(m),(),()->(n,4),(n,3),(n,6,6),(n,m,3),(n),(n),(n)"


# ------------------------------------------------------------------ checks


def _cov6(p: object, name: str) -> Array:
    p = _checks.as_float_array(p, name)
    if p.ndim < 2 or p.shape[-2:] != (6, 6):
        raise ValueError(f"argument '{name}' must be a covariance shaped (..., 6, 6), got shape {tuple(p.shape)}")
    return p


def _noise(x: object, name: str) -> Array:
    x = _checks.scalar_like(x, name)
    values = _checks.concrete(x)
    if values is not None and (not np.all(np.isfinite(values)) or np.any(values < 0)):
        raise ValueError(f"argument '{name}' must be finite and non-negative, got {values}")
    return x


def _vectors(body: object, ref: object, leading: str) -> tuple[Array, Array]:
    """Validate a measurement set: ``vectors_body``/``vectors_ref`` shaped ``(..., <leading> m, 3)``."""
    body = _checks.vec3(body, "vectors_body")
    ref = _checks.vec3(ref, "vectors_ref")
    core = 2 + len(leading.split())
    shape = "(..., " + (leading + ", " if leading else "") + "m, 3)"
    for arr, name in ((body, "vectors_body"), (ref, "vectors_ref")):
        if arr.ndim < core:
            raise ValueError(f"argument '{name}' must be shaped {shape}, got shape {tuple(arr.shape)}")
    try:  # the reference directions may be given once for all samples: n = 1 broadcasts
        same = jnp.broadcast_shapes(body.shape[-core:], ref.shape[-core:]) == body.shape[-core:]
    except ValueError:
        same = False
    if not same:
        raise ValueError(
            f"arguments 'vectors_body' and 'vectors_ref' must be shaped {shape} with the same "
            f"{leading + ', ' if leading else ''}m (or 1 in 'vectors_ref'), got {tuple(body.shape)} and "
            f"{tuple(ref.shape)}"
        )
    ref = jnp.broadcast_to(ref, ref.shape[:-core] + body.shape[-core:])
    return body, ref


def _state(state: FilterState) -> tuple[Array, Array, Array]:
    if not isinstance(state, tuple) or len(state) != 3:
        raise TypeError(f"argument 'state' must be a FilterState (q, bias, P), got {type(state).__name__}")
    return _checks.quat(state[0], "state.q"), _checks.vec3(state[1], "state.bias"), _cov6(state[2], "state.P")


# ------------------------------------------------------------------ public


def mekf_init(
    q0: Float[ArrayLike, "*#batch 4"], bias0: Float[ArrayLike, "*#batch 3"], P0: Float[ArrayLike, "*#batch 6 6"]
) -> FilterState:
    """The filter state at ``t_0``: ``q0`` (normalised here), ``bias0`` (rad/s) and the covariance
    ``P0`` of ``(dtheta, dbias)`` (rad^2, rad^2/s^2; the attitude block is body-frame)."""
    q0, bias0, p0 = _checks.quat(q0, "q0"), _checks.vec3(bias0, "bias0"), _cov6(P0, "P0")
    q0, bias0, p0 = _checks.broadcast_batch([q0, bias0, p0], ["q0", "bias0", "P0"], [1, 1, 2])
    return FilterState(q0 / jnp.linalg.norm(q0, axis=-1, keepdims=True), bias0, p0)


def mekf_predict(
    state: FilterState,
    gyro: Float[ArrayLike, "*#batch 3"],
    dt: Float[ArrayLike, "*#batch"] | float,
    *,
    gyro_noise,
    bias_noise,
) -> FilterState:
    """Propagate the estimate over ``dt`` with the gyro sample ``gyro`` (rad/s, body frame) held.

    ``q <- q Exp((gyro - bias) dt)`` (exact for a rate held over the step; no first-order
    integration), ``bias`` unchanged, ``P <- Phi P Phi^T + Q`` (``Phi`` and ``Q`` in the module
    docstring). ``gyro_noise``, ``bias_noise``: the spectral densities'
    square roots ``sigma_v`` (rad/s^(1/2)) and ``sigma_u`` (rad/s^(3/2)).
    """
    args = predict_args(state, gyro, dt, gyro_noise, bias_noise)
    return FilterState(*vectorized(_predict, PREDICT_SIGNATURE, (), *args))


PREDICT_SIGNATURE = "(4),(3),(6,6),(3),(),(),()->(4),(3),(6,6)"
UPDATE_SIGNATURE = "(4),(3),(6,6),(m,3),(m,3),(m)->(4),(3),(6,6),(m,3),(),(),()"


def predict_args(state, gyro, dt, gyro_noise, bias_noise) -> list[Array]:
    q, bias, p = _state(state)
    gyro = _checks.vec3(gyro, "gyro")
    dt, sv, su = _checks.scalar_like(dt, "dt"), _noise(gyro_noise, "gyro_noise"), _noise(bias_noise, "bias_noise")
    return _checks.broadcast_batch(
        [q, bias, p, gyro, dt, sv, su],
        ["q", "bias", "P", "gyro", "dt", "gyro_noise", "bias_noise"],
        [1, 1, 2, 1, 0, 0, 0],
    )


QUATERNION_SIGNATURE = "(4),(3),(6,6),(4),()->(4),(3),(6,6),(1,3),(),(),()"


def quaternion_args(state, q_meas, noise) -> list[Array]:
    q, bias, p = _state(state)
    q_meas, s = _checks.quat(q_meas, "q_meas"), _noise(noise, "noise")
    return _checks.broadcast_batch([q, bias, p, q_meas, s], ["q", "bias", "P", "q_meas", "noise"], [1, 1, 2, 1, 0])


def update_args(state, vectors_body, vectors_ref, vector_noise) -> list[Array]:
    q, bias, p = _state(state)
    body, ref = _vectors(vectors_body, vectors_ref, "")
    sigma = _sigma(vector_noise, "vector_noise", body.shape[-2])
    return _checks.broadcast_batch(
        [q, bias, p, body, ref, sigma],
        ["q", "bias", "P", "vectors_body", "vectors_ref", "vector_noise"],
        [1, 1, 2, 2, 2, 1],
    )


def _sigma(noise: object, name: str, m: int) -> Array:
    s = _noise(noise, name)
    if s.ndim == 0:
        return jnp.broadcast_to(s, (m,))
    if s.shape[-1] != m:
        raise ValueError(
            f"argument '{name}' must be a scalar or shaped (..., m) with m = {m} (one per sensor), "
            f"got shape {tuple(s.shape)}"
        )
    return s


def mekf_update(
    state: FilterState,
    vectors_body: Float[ArrayLike, "*#batch m 3"],
    vectors_ref: Float[ArrayLike, "*#batch m 3"],
    *,
    vector_noise: Float[ArrayLike, "*#batch m"] | float,
) -> tuple[FilterState, FilterUpdate]:
    """Update with ``m`` vector measurements at one time: ``b_i = R(q)^T r_i + v_i``.

    Measurement matrix rows ``H_i = [[b_hat_i x], 0]`` with ``b_hat_i = R(q)^T r_i`` (the
    body-frame error form of Markley & Crassidis' vector measurement model), all ``m`` vectors at once with
    ``R = diag(vector_noise_i^2 I_3)``; gain ``K = P H^T S^-1``, ``S = H P H^T + R`` (Cholesky),
    Joseph-form covariance, reset ``q <- q Exp(dtheta)``, ``bias <- bias + dbias``.

    A row with a NaN in either ``vectors_body`` or ``vectors_ref`` is a missing measurement: it
    is left out (its innovation is returned as 0 and it adds no degrees of freedom). With
    ``R = s^2 I`` the component of a unit-vector innovation along ``b`` is second order (the
    QUEST measurement model, Shuster 1989): the estimate is unaffected, but for normalised unit
    vectors the NIS has about 2, not 3, degrees of freedom per vector.
    """
    args = update_args(state, vectors_body, vectors_ref, vector_noise)
    return apply_update(_update_vectors, UPDATE_SIGNATURE, args)


def mekf_update_quaternion(
    state: FilterState, q_meas: Float[ArrayLike, "*#batch 4"], *, noise: Float[ArrayLike, "*#batch"] | float
) -> tuple[FilterState, FilterUpdate]:
    """Update with a measured attitude ``q_meas = q_true Exp(v)``, ``v ~ N(0, noise^2 I)`` (rad).

    Innovation ``Log(q* q_meas)`` (the body-frame rotation vector from the estimate to the
    measurement; either sign of ``q_meas``), ``H = [I, 0]``. A NaN in ``q_meas`` means no
    measurement. The innovation is returned shaped ``(..., 1, 3)``.
    """
    args = quaternion_args(state, q_meas, noise)
    return apply_update(_update_quaternion, QUATERNION_SIGNATURE, args)


def mekf(
    q0: Float[ArrayLike, "*#batch 4"],
    bias0: Float[ArrayLike, "*#batch 3"],
    P0: Float[ArrayLike, "*#batch 6 6"],
    dt: Float[ArrayLike, "*#batch"] | float,
    gyro: Float[ArrayLike, "*#batch n 3"],
    vectors_body: Float[ArrayLike, "*#batch n m 3"],
    vectors_ref: Float[ArrayLike, "*#batch n m 3"],
    *,
    vector_noise: Float[ArrayLike, "*#batch m"] | float,
    gyro_noise: Float[ArrayLike, "*#batch"] | float,
    bias_noise: Float[ArrayLike, "*#batch"] | float,
) -> FilterResult:
    """Run the MEKF over a whole record in one ``lax.scan`` (Crassidis & Junkins, Table 7.1).

    Samples are taken every ``dt`` at ``t_k = t_0 + k dt``: ``gyro[k]`` and the vector
    measurements ``vectors_body[k]`` (body frame) of the known directions ``vectors_ref[k]``
    (reference frame). ``(q0, bias0, P0)`` is the prior at ``t_0``. Row ``k`` of the result is
    the estimate at ``t_k`` after the update with the measurements of ``t_k``; between ``t_{k-1}``
    and ``t_k`` the filter propagates with ``gyro[k-1]`` held (so ``gyro[n-1]`` is not used). A row
    of NaN in ``vectors_body`` or ``vectors_ref`` is a missing measurement (:func:`mekf_update`).

    Noise: ``vector_noise`` per sensor (a scalar or ``(..., m)``, radians), ``gyro_noise`` and
    ``bias_noise`` as in :func:`mekf_predict`. All arguments broadcast over leading batch axes, so a
    Monte Carlo of many runs is one call (or ``vmap``); everything is differentiable, including
    with respect to the noise parameters (the innovations' log-likelihood is in the result).

    Args:
        q0: prior attitude ``(..., 4)`` (reference to body; normalised here).
        bias0: prior gyro bias ``(..., 3)`` (rad/s).
        P0: prior covariance of ``(dtheta, dbias)``, ``(..., 6, 6)``.
        dt: the sample interval (s).
        gyro: rate-gyro samples ``(..., n, 3)`` (rad/s, body frame).
        vectors_body: measured directions ``(..., n, m, 3)`` (body frame; NaN rows missing).
        vectors_ref: the same directions in the reference frame ``(..., n, m, 3)``.
        vector_noise: per-sensor angular noise (rad), a scalar or ``(..., m)``.
        gyro_noise: gyro rate noise density (rad/s/sqrt(Hz)).
        bias_noise: bias random-walk density (rad/s^2/sqrt(Hz)).

    Returns:
        A :class:`FilterResult`, one row per sample: ``q``, ``bias``, ``P``, the normalised
        innovations ``nis`` and the ``log_likelihood`` of the record.
    """
    args = record(q0, bias0, P0, dt, gyro, vectors_body, vectors_ref, vector_noise, gyro_noise, bias_noise)
    return FilterResult(
        *jnp.vectorize(functools.partial(scan, _predict, _update_vectors), signature=RECORD_SIGNATURE)(*args)
    )


def record(q0, bias0, P0, dt, gyro, vectors_body, vectors_ref, vector_noise, gyro_noise, bias_noise) -> list[Array]:
    """Validate a whole-record filter call and broadcast its batch axes (the runners' arguments)."""
    q0, bias0, p0 = mekf_init(q0, bias0, P0)
    gyro = _checks.vec3(gyro, "gyro")
    if gyro.ndim < 2 or gyro.shape[-2] == 0:
        raise ValueError(
            f"argument 'gyro' must be shaped (..., n, 3) with n >= 1 samples, got shape {tuple(gyro.shape)}"
        )
    body, ref = _vectors(vectors_body, vectors_ref, "n")
    if body.shape[-3] != gyro.shape[-2]:
        raise ValueError(
            f"arguments 'gyro' (..., n, 3) and 'vectors_body' (..., n, m, 3) must have the same n, got "
            f"{tuple(gyro.shape)} and {tuple(body.shape)}"
        )
    sigma = _sigma(vector_noise, "vector_noise", body.shape[-2])
    dt, sv, su = _checks.scalar_like(dt, "dt"), _noise(gyro_noise, "gyro_noise"), _noise(bias_noise, "bias_noise")
    names = [
        "q0",
        "bias0",
        "P0",
        "dt",
        "gyro",
        "vectors_body",
        "vectors_ref",
        "vector_noise",
        "gyro_noise",
        "bias_noise",
    ]
    return _checks.broadcast_batch(
        [q0, bias0, p0, dt, gyro, body, ref, sigma, sv, su], names, [1, 1, 2, 0, 2, 3, 3, 1, 0, 0]
    )
