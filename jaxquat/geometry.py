"""Geometry and statistics of rotations: angles, distances, averaging, Wahba's problem, sampling."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import Float

from . import _checks, _quaternion, _rotation, _safe, _trig

__all__ = ["angle", "angle_between", "mean", "align_vectors", "random"]


def _angle(q: Array) -> Array:
    w = q[..., 0]
    return 2.0 * _trig.atan2(_safe.safe_norm(q[..., 1:]), _safe.safe_sqrt(w * w))


def angle(q: Float[Array, "*batch 4"]) -> Float[Array, "*batch"]:
    """Rotation angle ``phi = 2 atan2(|v|, |w|)`` in ``[0, pi]`` ([T] eq. (32a), without ``acos``).

    Scale-invariant. ``phi`` is not differentiable at the identity (it is the
    cone ``2|v|``); there the gradient returned is the zero subgradient. At 180
    degrees (``w = 0``) the gradient with respect to ``w`` is 0 (a maximum).
    """
    return _angle(_safe.rescaled(_checks.quat(q)))


def angle_between(p: Float[Array, "*batch 4"], q: Float[Array, "*batch 4"]) -> Float[Array, "*batch"]:
    """Geodesic distance on SO(3): the angle of the relative rotation ``p* q``, in ``[0, pi]``.

    Symmetric in ``p`` and ``q`` and invariant to the sign of either. Assumes unit inputs.
    """
    p = _checks.quat(p, "p")
    q = _checks.quat(q, "q")
    p, q = _checks.broadcast_batch([p, q], ["p", "q"], [1, 1])
    return _angle(_quaternion.multiply(_quaternion.conjugate(p), q))


def mean(q: Float[Array, "*batch n 4"], weights: Float[Array, "*batch n"] | None = None) -> Float[Array, "*batch 4"]:
    """Chordal L2 mean of rotations (Markley, Cheng, Crassidis & Oshman 2007).

    The unit eigenvector of the largest eigenvalue of ``M = sum_i w_i q_i q_i^T``
    (a 4x4 ``eigh``), which minimises ``sum_i w_i |R(q) - R(q_i)|_F^2``. Reduces
    the second-to-last axis (``n`` rotations); leading axes are batch axes.
    Invariant to the sign of each ``q_i``; returns the canonical sign
    (``w >= 0``). Default weights all ones. Gradients exist where the top
    eigenvalue is simple.

    Bad input: an empty set (``n = 0``) raises ``ValueError`` at trace time.
    Weights must be finite and non-negative with a positive sum: checked with a
    ``ValueError`` when their values are known (an eager call); under ``jit`` a
    set with a negative or non-finite weight, or all weights zero, gives NaN.
    """
    q = _checks.quat(q)
    if q.ndim < 2:
        raise ValueError(
            f"argument 'q' must be shaped (..., n, 4) with n rotations to average, got shape {tuple(q.shape)}"
        )
    _checks.nonempty(q, "q", -2, "rotation to average (n >= 1 in (..., n, 4))")
    if weights is None:
        return _rotation.top_eigenvector(jnp.einsum("...ni,...nj->...ij", q, q))
    weights = _checks.weights(_checks.per_item(weights, "weights", q, "q"))
    q, weights = _checks.broadcast_batch([q, weights], ["q", "weights"], [2, 1])
    m = jnp.einsum("...n,...ni,...nj->...ij", weights, q, q)
    return _nan_where(~_valid_weights(weights), _rotation.top_eigenvector(m))


def _valid_weights(weights: Array) -> Array:
    """Per set: every weight finite and non-negative, and their sum positive."""
    ok = jnp.all(jnp.isfinite(weights) & (weights >= 0), axis=-1)
    return ok & (jnp.sum(weights, axis=-1) > 0)


def _nan_where(bad: Array, q: Array) -> Array:
    """NaN in every component of the elements where ``bad`` (the others untouched)."""
    return jnp.where(bad[..., None], jnp.nan, q)


def align_vectors(
    a: Float[Array, "*batch n 3"],
    b: Float[Array, "*batch n 3"],
    weights: Float[Array, "*batch n"] | None = None,
    *,
    return_sensitivity: bool = False,
) -> Float[Array, "*batch 4"] | tuple[Float[Array, "*batch 4"], Float[Array, "*batch 3 3"]]:
    """Rotation ``q`` minimising ``sum_i w_i |a_i - R(q) b_i|^2`` (Wahba's problem).

    Solved by Davenport's q-method: ``q`` is the top eigenvector of
    ``K = [[tr B, z^T], [z, B + B^T - tr(B) I]]`` with ``B = sum_i w_i a_i b_i^T``
    and ``z = (B21 - B12, B02 - B20, B10 - B01)``, since
    ``q^T K q = sum_i w_i a_i . R(q) b_i``. The same convention as scipy's
    ``Rotation.align_vectors(a, b)``: ``a ~ R b``. Canonical sign (``w >= 0``).

    With a single vector pair (``n == 1``, known at trace time) the problem is
    underdetermined; the minimal rotation taking ``b`` onto ``a`` is returned
    (Horn's closed form ``normalize(|a||b| + a.b, b x a)``; a rotation by pi
    about an axis perpendicular to ``b`` when they are antiparallel). With
    ``n >= 2`` vectors all parallel the answer is likewise not unique and the
    gradient does not exist.

    With ``return_sensitivity=True`` the result is ``(q, S)`` with scipy's sensitivity matrix
    ``S = mean(w) (kappa I + B B^T) / zeta``, ``kappa = (lambda^2 - |B|_F^2) / 2``,
    ``zeta = lambda kappa - det B`` (``lambda = q^T K q``, the sum of ``B``'s proper singular
    values; Markley & Crassidis 2014, section 5.5). It is the covariance of the error rotation
    vector in the frame of ``a`` (``q_true = Exp(e) q``) divided by the variance of one unit-weight
    measurement: with weights ``1/s_i^2`` and unit vectors, ``S / mean(w)`` is that covariance,
    ``(sum_i w_i (I - a_i a_i^T))^-1`` to first order. Needs ``n >= 2`` (a ``ValueError`` otherwise).

    Bad input: no vectors (``n = 0``) raises ``ValueError`` at trace time; weights
    are checked as in :func:`mean`. A problem with no information (a zero vector
    when ``n == 1``; every weighted product ``a_i b_i^T`` zero, e.g. all vectors
    zero) gives NaN for that element, under ``jit`` or not.
    """
    a, b, weights = _checks.vector_pairs(a, b, weights, ("a", "b"))
    if weights is None:
        weights = jnp.ones(a.shape[:-1], a.dtype)
        bad = jnp.zeros(a.shape[:-2], bool)
    else:
        bad = ~_valid_weights(weights)
    if return_sensitivity and a.shape[-2] == 1:
        raise ValueError(
            "align_vectors(..., return_sensitivity=True) needs at least two vector pairs (n >= 2 in "
            f"(..., n, 3)): a single vector pair leaves the rotation about it undetermined, got shape {tuple(a.shape)}"
        )
    if a.shape[-2] == 1:
        degenerate = (_safe.norm_sq(a[..., 0, :]) == 0) | (_safe.norm_sq(b[..., 0, :]) == 0)
        return _nan_where(bad | degenerate, _rotation.minimal_rotation(a[..., 0, :], b[..., 0, :]))
    bmat = jnp.einsum("...n,...ni,...nj->...ij", weights, a, b)
    k = _rotation.k_matrix(bmat)
    q = _nan_where(bad | jnp.all(bmat == 0, axis=(-2, -1)), _rotation.top_eigenvector(k))
    if not return_sensitivity:
        return q
    return q, _sensitivity(k, q, bmat, weights)


def _sensitivity(k: Array, q: Array, bmat: Array, weights: Array) -> Array:
    """scipy's ``align_vectors`` sensitivity from Davenport's eigenpair, without an SVD: with ``s_i``
    the proper singular values of ``B``, ``lambda = s_1 + s_2 + s_3``, ``kappa = sum_{i<j} s_i s_j``
    and ``zeta = prod_{i<j} (s_i + s_j)``, written through ``tr(B B^T)`` and ``det B``."""
    lam = jnp.einsum("...i,...ij,...j->...", q, k, q)
    bbt = jnp.einsum("...ik,...jk->...ij", bmat, bmat)
    kappa = 0.5 * (lam * lam - jnp.trace(bbt, axis1=-2, axis2=-1))
    zeta = lam * kappa - jnp.linalg.det(bmat)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=bmat.dtype), bbt.shape)
    scale = jnp.mean(weights, axis=-1) / zeta
    return scale[..., None, None] * (kappa[..., None, None] * eye + bbt)


def random(key: Array, shape: tuple[int, ...] | int = (), dtype: Any = None) -> Float[Array, "*shape 4"]:
    """Rotations drawn uniformly from SO(3) (Haar measure): normalised 4-D Gaussians.

    An isotropic Gaussian in R^4 normalised to S^3 is uniform on S^3, and S^3
    covers SO(3) twice uniformly. ``dtype`` defaults to JAX's default float.
    """
    if isinstance(shape, int):
        shape = (shape,)
    dtype = _checks.float_dtype(dtype)
    g = jax.random.normal(key, tuple(shape) + (4,), dtype=dtype)
    return g / jnp.sqrt(_safe.norm_sq(g))[..., None]
