"""Geometry of rotations: the angle of a rotation, the angle between two, and the chordal mean of a set.

Wahba's problem (``align_vectors``) lives with the other attitude-determination methods in
:mod:`jaxquat.rotations.determination`; uniform random rotations (``random``) beside ``identity`` in
:mod:`jaxquat.rotations.algebra`.
"""

from __future__ import annotations


from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation, _safe, _trig

__all__ = ["angle", "angle_between", "mean"]


def _angle(q: Array) -> Array:
    w = q[..., 0]
    return 2.0 * _trig.atan2(_safe.safe_norm(q[..., 1:]), _safe.safe_sqrt(w * w))


def angle(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch"]:
    """Rotation angle ``phi = 2 atan2(|v|, |w|)`` in ``[0, pi]`` ([T] eq. (32a), without ``acos``).

    Scale-invariant. ``phi`` is not differentiable at the identity (it is the
    cone ``2|v|``); there the gradient returned is the zero subgradient. At 180
    degrees (``w = 0``) the gradient with respect to ``w`` is 0 (a maximum).
    """
    return _arrays.compiled_rows(_rescaled_angle, (1,), _checks.quat(q))


def _rescaled_angle(q: Array) -> Array:
    return _angle(_safe.rescaled(q))


def angle_between(p: Float[ArrayLike, "*#batch 4"], q: Float[ArrayLike, "*#batch 4"]) -> Float[Array, "*batch"]:
    """Geodesic distance on SO(3): the angle of the relative rotation ``p* q``, in ``[0, pi]``.

    Symmetric in ``p`` and ``q`` and invariant to the sign of either. Assumes unit inputs.
    """
    p, q = _checks.arguments(p=(p, "quaternion"), q=(q, "quaternion"), shared=True)
    return _arrays.compiled_rows(_angle_between, (1, 1), p, q)


def _angle_between(p: Array, q: Array) -> Array:
    # On components: p* q = (p . q, vec(p* q)), the angle 2 atan2(|vec|, |p . q|). Through
    # multiply's rows (until session 53), 10^5 pairs, one core, least of 7, value / gradient of
    # sum(f * W) in p: float32 0.82 / 3.3 -> 0.81 / 1.2 ms, float64 1.55 / 6.6 -> 1.55 / 2.7 ms.
    pc, qc = _arrays.components(p), _arrays.components(q)
    w, x, y, z = _quaternion.multiply_dense([pc[0], -pc[1], -pc[2], -pc[3]], qc)
    return 2.0 * _trig.atan2(_safe.safe_sqrt(x * x + y * y + z * z), _safe.safe_sqrt(w * w))


def mean(
    q: Float[ArrayLike, "*#batch n 4"], weights: Float[ArrayLike, "*#batch n"] | None = None
) -> Float[Array, "*batch 4"]:
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
        return _arrays.compiled(_mean, q)
    weights = _checks.weights(_checks.per_item(weights, "weights", q, "q"))
    q, weights = _checks.arguments(q=(q, "quaternions"), weights=(weights, "scalars"))
    return _arrays.compiled(_weighted_mean, q, weights)


def _mean(q: Array) -> Array:
    return _rotation.top_eigenvector(_arrays.outer_sum(q))


def _weighted_mean(q: Array, weights: Array) -> Array:
    m = _arrays.outer_sum(q, weights=weights)
    return _arrays.nan_where(~_arrays.valid_weights(weights), _rotation.top_eigenvector(m))
