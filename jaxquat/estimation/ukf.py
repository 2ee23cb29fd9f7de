"""An unscented Kalman filter on the rotation group for attitude and gyro bias.

The sigma points live on the group, as in Crassidis & Markley's USQUE (2003) and the UKF-M of
Brossard, Barrau & Bonnabel (2020), written with this library's retraction: with the error state
``x = (dtheta, dbias)`` (``q_true = q Exp(dtheta)``, body frame, as in :mod:`jaxquat.estimation.mekf`) and
``L L^T = (6 + kappa) P``, the 13 points are ``q Exp(d_i)``, ``bias + e_i`` for
``(d_i, e_i) = 0, +-L[:, j]``, with Julier's weights ``kappa / (6 + kappa)`` (centre) and
``1 / (2 (6 + kappa))``; ``kappa = 1`` by default, which keeps every weight positive.

* predict: each point is turned by its own bias-corrected rate, ``q_i Exp((gyro - bias_i) dt)``
  (exact for the held rate), and read back as ``minus(q_i', q_0')`` about the propagated centre;
  the weighted mean moves the estimate (``q' = q_0' Exp(mean)``) and the spread, plus the
  discrete process noise ``Q`` of the MEKF, is the new ``P``. Nothing is linearised: no ``Phi``.
* update: the points' predicted measurements ``R(q_i)^T r`` give ``P_zz`` (plus ``R``) and
  ``P_xz``; ``K = P_xz P_zz^-1``, reset ``q <- q Exp(dtheta)``, ``P <- P - K P_zz K^T``.

Measurements and noise are as in :mod:`jaxquat.estimation.mekf` (NaN rows are missing, same statistics),
and the state and result types are shared with it. Unlike the MEKF, the sigma points need a
Cholesky factor of ``P``: a ``P`` that is not positive definite (a correlation of exactly 1, say)
gives NaN, where the MEKF would carry it on.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation
from .mekf import (
    PREDICT_SIGNATURE,
    QUATERNION_SIGNATURE,
    RECORD_SIGNATURE,
    UPDATE_SIGNATURE,
    FilterResult,
    FilterState,
    FilterUpdate,
    apply_update,
    vectorized,
    innovate,
    masked,
    predict_args,
    process_noise,
    quaternion_innovation,
    quaternion_args,
    record,
    scan,
    statistics,
    symmetric,
    update_args,
)

__all__ = ["ukf_predict", "ukf_update", "ukf_update_quaternion", "ukf"]


def _points(q, bias, p, kappa):
    """The 13 sigma points (quaternions (13, 4), biases (13, 3)), their offsets (13, 6), weights."""
    n = p.shape[-1]
    chol = jnp.linalg.cholesky((n + kappa) * symmetric(p))
    offsets = jnp.concatenate([jnp.zeros((1, n), p.dtype), chol.T, -chol.T], axis=0)
    weights = jnp.concatenate([jnp.full((1,), kappa / (n + kappa)), jnp.full((2 * n,), 0.5 / (n + kappa))]).astype(
        p.dtype
    )
    qs = _quaternion.multiply(jnp.broadcast_to(q, (2 * n + 1, 4)), _rotation.from_rotvec(offsets[:, :3]))
    return qs, bias[None, :] + offsets[:, 3:], offsets, weights


def _predict(q, bias, p, gyro, dt, gyro_noise, bias_noise, kappa):
    qs, biases, offsets, w = _points(q, bias, p, kappa)
    qs = _quaternion.multiply(qs, _rotation.from_rotvec((gyro[None, :] - biases) * dt))
    centre = qs[0]
    dev = jnp.concatenate(
        [
            _rotation.to_rotvec(_quaternion.multiply(jnp.broadcast_to(_quaternion.conjugate(centre), qs.shape), qs)),
            offsets[:, 3:],
        ],
        -1,
    )
    mm = _arrays.matmul
    mean = mm(w, dev)
    spread = dev - mean[None, :]
    p = symmetric(mm((spread * w[:, None]).T, spread) + process_noise(dt, gyro_noise, bias_noise, p.dtype))
    return _quaternion.multiply(centre, _rotation.from_rotvec(mean[:3])), bias + mean[3:], p


def _unscented_update(q, bias, p, offsets, w, z, measured, r_diag):
    """The update from the points' predicted measurements ``z`` (13, k) against ``measured`` (k,):
    ``P_zz`` (plus ``diag(r_diag)``), ``P_xz``, then the MEKF's gain and reset; ``P <- P - K P_zz K^T``."""
    mm = _arrays.matmul
    z_mean = mm(w, z)
    dz = z - z_mean[None, :]
    pzz = symmetric(mm((dz * w[:, None]).T, dz) + jnp.diag(r_diag))
    pxz = mm((offsets * w[:, None]).T, dz)
    residual = measured - z_mean
    gain, q, bias, nis, logdet = innovate(q, bias, pzz, pxz.T, residual)
    return (q, bias, symmetric(p - mm(mm(gain, pzz), gain.T))), residual, nis, logdet


def _update_vectors(q, bias, p, body, ref, sigma, kappa):
    valid, body, ref = masked(body, ref)
    m = body.shape[0]
    qs, _, offsets, w = _points(q, bias, p, kappa)
    conj = _quaternion.conjugate(qs)[:, None, :]
    z = _quaternion.rotate(jnp.broadcast_to(conj, (qs.shape[0], m, 4)), jnp.broadcast_to(ref, (qs.shape[0], m, 3)))
    z = (z * valid[None, :, None]).reshape(qs.shape[0], 3 * m)
    r_diag = jnp.repeat(jnp.where(valid, sigma * sigma, 1.0), 3)
    measured = jnp.where(valid[:, None], body, 0.0).reshape(-1)
    state, residual, nis, logdet = _unscented_update(q, bias, p, offsets, w, z, measured, r_diag)
    return state, (residual.reshape(m, 3), nis, *statistics(nis, logdet, valid))


def _update_quaternion(q, bias, p, q_meas, sigma, kappa):
    # The points' predicted measurement, read in the tangent space at the estimate, is their own
    # attitude offset minus(q_i, q) = d_i: the unscented update is then exactly the linear one.
    valid, measured = quaternion_innovation(q, q_meas)
    _, _, offsets, w = _points(q, bias, p, kappa)
    r_diag = jnp.full((3,), jnp.where(valid, sigma * sigma, 1.0))
    state, residual, nis, logdet = _unscented_update(q, bias, p, offsets, w, offsets[:, :3] * valid, measured, r_diag)
    return state, (residual[None], nis, *statistics(nis, logdet, valid))


def _kappa(kappa: float) -> float:
    if _checks.is_traced(kappa) or not np.isfinite(kappa) or kappa <= 0:
        raise ValueError(f"argument 'kappa' must be a positive Python float (the sigma-point spread), got {kappa!r}")
    return float(kappa)


def ukf_predict(
    state: FilterState,
    gyro: Float[ArrayLike, "*#batch 3"],
    dt: Float[ArrayLike, "*#batch"] | float,
    *,
    gyro_noise,
    bias_noise,
    kappa: float = 1.0,
) -> FilterState:
    """Propagate the estimate over ``dt`` through 13 sigma points on the group (module docstring).

    Same arguments and noise model as :func:`jaxquat.mekf_predict`; ``kappa`` sets the spread.
    """
    args = predict_args(state, gyro, dt, gyro_noise, bias_noise)
    return FilterState(*vectorized(_predict, PREDICT_SIGNATURE, (("kappa", _kappa(kappa)),), *args))


def ukf_update(
    state: FilterState,
    vectors_body: Float[ArrayLike, "*#batch m 3"],
    vectors_ref: Float[ArrayLike, "*#batch m 3"],
    *,
    vector_noise: Float[ArrayLike, "*#batch m"] | float,
    kappa: float = 1.0,
) -> tuple[FilterState, FilterUpdate]:
    """Update with ``m`` vector measurements ``b_i = R(q)^T r_i + v_i`` through the sigma points'
    predicted measurements (module docstring). Arguments, missing rows and the returned statistics
    as in :func:`jaxquat.mekf_update`."""
    args = update_args(state, vectors_body, vectors_ref, vector_noise)
    return apply_update(_update_vectors, UPDATE_SIGNATURE, args, (("kappa", _kappa(kappa)),))


def ukf_update_quaternion(
    state: FilterState,
    q_meas: Float[ArrayLike, "*#batch 4"],
    *,
    noise: Float[ArrayLike, "*#batch"] | float,
    kappa: float = 1.0,
) -> tuple[FilterState, FilterUpdate]:
    """Update with a measured attitude ``q_meas = q_true Exp(v)``, ``v ~ N(0, noise^2 I)`` (rad),
    through the sigma points: read in the tangent space at the estimate the measurement is linear
    in the error (``minus(q_i, q) = d_i``), so this equals :func:`jaxquat.mekf_update_quaternion`
    to rounding. A NaN in ``q_meas`` means no measurement."""
    args = quaternion_args(state, q_meas, noise)
    return apply_update(_update_quaternion, QUATERNION_SIGNATURE, args, (("kappa", _kappa(kappa)),))


def ukf(
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
    kappa: float = 1.0,
) -> FilterResult:
    """The unscented filter over a whole record in one ``lax.scan``: the same arguments, sample
    timing and result as :func:`jaxquat.mekf` (row ``k`` is the estimate at ``t_0 + k dt`` after
    the update with the measurements of that time), with sigma points instead of linearisation."""
    args = record(q0, bias0, P0, dt, gyro, vectors_body, vectors_ref, vector_noise, gyro_noise, bias_noise)
    k = _kappa(kappa)
    run = functools.partial(scan, functools.partial(_predict, kappa=k), functools.partial(_update_vectors, kappa=k))
    return FilterResult(*jnp.vectorize(run, signature=RECORD_SIGNATURE)(*args))
