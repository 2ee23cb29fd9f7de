"""Quaternion algebra: product, conjugate, inverse, norm, exp/log/power, 4x4 product matrices,
the identity and uniform random rotations.

Conventions (all of jaxquat): arrays shaped ``(..., 4)``, scalar first
``(w, x, y, z)``; Hamilton product (``i j = k``); leading axes are batch axes
and broadcast. Every function here is written element-wise on the four
components, so XLA fuses a whole expression into one loop over the batch.

Source documents: Tasora, "Rotations in Chrono::Engine" (2016) [T];
Chou, "Quaternion kinematic and dynamic differential equations" (1992) [C];
Schwab, "Quaternions, finite rotation and Euler parameters" (2002) [S].
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _safe

__all__ = [
    "multiply",
    "conjugate",
    "inverse",
    "norm",
    "normalize",
    "identity",
    "random",
    "exp",
    "log",
    "power",
    "left_matrix",
    "right_matrix",
    "rotate",
    "canonicalize",
]


def multiply(p: Float[ArrayLike, "*#batch 4"], q: Float[ArrayLike, "*#batch 4"]) -> Float[Array, "*batch 4"]:
    """Hamilton product ``p q``.

    ``(p0, p) (q0, q) = (p0 q0 - p.q,  p0 q + q0 p + p x q)``: [T] eq. (5) and
    (17b), [C] eqs. (7)-(9), [S] eq. (2). ``multiply(p, q)`` rotates by ``q``
    first, then by ``p`` (active convention). Exact for any quaternions, unit or
    not; batch axes broadcast.
    """
    p, q = _checks.arguments(p=(p, "quaternion"), q=(q, "quaternion"), shared=True)
    return _arrays.compiled_rows_broadcast(_quaternion.multiply, (1, 1), p, q)


def conjugate(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Conjugate ``q* = (q0, -q)``, [T] eq. (9). The inverse rotation for unit ``q``."""
    return _arrays.compiled_rows(_quaternion.conjugate, (1,), _checks.quat(q))


def norm(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch"]:
    """Euclidean norm ``|q| = sqrt(q q*)``, [T] eq. (12).

    The gradient at ``q = 0`` is 0 (a subgradient of the cone) instead of NaN.
    """
    return _arrays.compiled_rows(_safe.safe_norm, (1,), _checks.quat(q))


def normalize(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """``q / |q|``, [T] eq. (54).

    A zero quaternion has no direction: its result is NaN in all four
    components (so the bad element is visible), computed element-wise so the
    other elements of a jitted batch, and their gradients, are unaffected.
    """
    q = _checks.quat(q)
    # |q| from the components (their cotangents gathered by products, not pads of slices) and
    # repeated along the row (per_row: a broadcast's cotangent is a YNNPACK sum over the minor
    # axis on CPU): the gradient at 10^5 (float32, one core) 1.3 -> 0.3 ms
    c = _arrays.components(q)
    return q / _arrays.per_row(jnp.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3]), 4)


def inverse(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Multiplicative inverse ``q^-1 = q* / |q|^2`` of any non-zero quaternion, [T] eq. (14).

    For a zero quaternion the result is NaN (element-wise, as in :func:`normalize`).
    """
    return _arrays.compiled_rows(_inverse, (1,), _checks.quat(q))


def _inverse(q: Array) -> Array:
    """``q* / |q|^2``, the conjugate as a product with the signs ``(1, -1, -1, -1)`` and ``|q|^2``
    repeated along the row (:func:`jaxquat._arrays.per_row`), so that reverse mode transposes
    whole-row operations: with the conjugate stacked from components and ``|q|^2`` broadcast, the
    gradient at 10^5 (float32, one core) took 2.5 ms (the broadcast's transpose a YNNPACK sum over
    the minor axis) against 0.3 ms, the value 0.18 against 0.07 ms."""
    signs = jnp.asarray([1.0, -1.0, -1.0, -1.0], q.dtype).reshape((1,) * (q.ndim - 1) + (4,))
    return q * signs / _arrays.per_row(_safe.norm_sq(q), 4)


def identity(shape: tuple[int, ...] | int = (), dtype: Any = None) -> Float[Array, "*shape 4"]:
    """The identity rotation ``(1, 0, 0, 0)`` broadcast to ``shape + (4,)``.

    ``dtype`` defaults to JAX's default float dtype (float32 unless x64 is on).
    """
    if isinstance(shape, int):
        shape = (shape,)
    dtype = _checks.float_dtype(dtype)
    return jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype=dtype), tuple(shape) + (4,))


def _exp(q: Array) -> Array:
    w = q[..., 0]
    v = q[..., 1:]
    s = _safe.norm_sq(v)
    scale = jnp.exp(w)
    sinc, cos = _safe.sinc_cos_of_sq(s)
    return _quaternion.scalar_vector(scale * cos, v, scale * sinc)


def exp(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Quaternion exponential ``exp(w, v) = e^w (cos|v|, sin|v| v/|v|)``, [T] eqs. (55)-(56).

    Defined for every quaternion. ``sin|v|/|v|`` and ``cos|v|`` are evaluated as
    series in ``|v|^2`` near zero, so ``exp`` is smooth (all derivatives exact) at
    ``v = 0``; its Jacobian there is the identity on the vector part times ``e^w``.
    For a pure quaternion ``(0, phi u / 2)`` it is the unit quaternion of the
    rotation by ``phi`` about ``u``.
    """
    return _arrays.compiled_rows(_exp, (1,), _checks.quat(q))


def _log(q: Array) -> Array:
    w = q[..., 0]
    v = q[..., 1:]
    nsq = _safe.norm_sq(v)
    qsq = nsq + w * w
    factor = _safe.atan2_over_n(nsq, w)
    # Real negative quaternions: log is (ln|w|, pi, 0, 0), one of infinitely many.
    real_negative = (nsq == 0) & (w < 0)
    vec = _quaternion.scaled(factor, v)
    vec = jnp.where(real_negative[..., None], _arrays.const_like([jnp.pi, 0.0, 0.0], vec), vec)
    scalar = 0.5 * jnp.log(qsq)
    return _quaternion.scalar_vector(scalar, vec)


def log(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Principal quaternion logarithm ``log q = (ln|q|, atan2(|v|, w) v/|v|)``, [T] eq. (58).

    For a unit quaternion ``(cos(phi/2), sin(phi/2) u)`` this is the pure
    quaternion ``(0, phi u / 2)``; ``exp(log(q)) == q`` for every non-zero ``q``.
    ``atan2(|v|, w)/|v|`` is a series in ``|v|^2/w^2`` near the positive real
    axis, so ``log`` is smooth at the identity (Jacobian of the vector part is
    ``I/w``). The vector part has norm at most ``pi``: for ``w < 0`` it describes
    the rotation the long way round (use :func:`jaxquat.to_rotvec` for the
    shortest rotation vector). On the negative real axis the logarithm is not
    unique and its derivative does not exist; there the result is
    ``(ln|q|, pi, 0, 0)`` (a valid logarithm). ``log(0)`` is ``-inf`` in the scalar part.
    """
    return _arrays.compiled_rows(_log, (1,), _checks.quat(q))


def power(q: Float[ArrayLike, "*#batch 4"], t: Float[ArrayLike, "*#batch"] | float) -> Float[Array, "*batch 4"]:
    """Quaternion power ``q^t = exp(t log q)``, [T] eq. (57).

    For unit ``q = (cos(phi/2), sin(phi/2) u)``: ``q^t = (cos(t phi/2), sin(t phi/2) u)``,
    the rotation by ``t phi`` about ``u``. Works for any non-zero ``q``
    (``|q^t| = |q|^t``); ``t`` broadcasts against the batch axes of ``q``.
    Smooth at the identity; not differentiable on the negative real axis (see :func:`log`).
    """
    q, t = _checks.arguments(q=(q, "quaternion"), t=(t, "scalar"), shared=True)
    return _arrays.compiled_rows(_power, (1, 0), q, t)


def _power(q: Array, t: Array) -> Array:
    # On components, exp and log written on the parts (_log_parts, _exp_parts) with the scaling
    # between them. As _exp(t * _log(q)) on rows (until session 53), 10^5 rotations, one core,
    # least of 7, value / gradient of sum(f * W) in q: float32 1.3 / 5.5 -> 1.4 / 1.85 ms, float64
    # 3.2 / 11.2 -> 3.25 / 4.6 ms.
    return _arrays.assemble(*_exp_parts([t * x for x in _log_parts(_arrays.components(q))]))


def _log_parts(q: list[Array]) -> list[Array]:
    """:func:`_log` on components (the public ``log`` keeps the rows: on components its value took
    0.78 against 0.66 ms at 10^5, float32, though its gradient 1.1 against 1.8 ms)."""
    w, v = q[0], q[1:]
    nsq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    factor = _safe.atan2_over_n(nsq, w)
    real_negative = (nsq == 0) & (w < 0)  # as _log
    vec = [jnp.where(real_negative, c, factor * x) for c, x in zip((jnp.pi, 0.0, 0.0), v)]
    return [0.5 * jnp.log(nsq + w * w)] + vec


def _exp_parts(q: list[Array]) -> list[Array]:
    """:func:`_exp` on components (the public ``exp`` keeps the rows, as ``log``)."""
    w, v = q[0], q[1:]
    scale = jnp.exp(w)
    sinc, cos = _safe.sinc_cos_of_sq(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return [scale * cos] + [(scale * sinc) * x for x in v]


def left_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4 4"]:
    """The 4x4 matrix of left multiplication: ``multiply(q, p) == left_matrix(q) @ p``.

    ``[[q0, -q^T], [q, q0 I + q~]]``: Chou's "+" matrix [C] eq. (11), Schwab's
    ``Q`` [S] eq. (3), Tasora's ``[M(q)+]`` [T] eq. (20b).
    """
    return _arrays.compiled_rows(_left_matrix, (1,), _checks.quat(q))


def _left_matrix(q: Array) -> Array:
    w, x, y, z = _quaternion.split(q)
    return jnp.stack(
        [
            jnp.stack([w, -x, -y, -z], -1),
            jnp.stack([x, w, -z, y], -1),
            jnp.stack([y, z, w, -x], -1),
            jnp.stack([z, -y, x, w], -1),
        ],
        axis=-2,
    )


def right_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4 4"]:
    """The 4x4 matrix of right multiplication: ``multiply(p, q) == right_matrix(q) @ p``.

    ``[[q0, -q^T], [q, q0 I - q~]]``: Chou's "-" matrix [C] eq. (11), Schwab's
    ``Q-bar`` [S] eq. (3), Tasora's ``[M(q)-]`` [T] eq. (20c).
    """
    return _arrays.compiled_rows(_right_matrix, (1,), _checks.quat(q))


def _right_matrix(q: Array) -> Array:
    w, x, y, z = _quaternion.split(q)
    return jnp.stack(
        [
            jnp.stack([w, -x, -y, -z], -1),
            jnp.stack([x, w, z, -y], -1),
            jnp.stack([y, -z, w, x], -1),
            jnp.stack([z, y, -x, w], -1),
        ],
        axis=-2,
    )


def rotate(q: Float[ArrayLike, "*#batch 4"], v: Float[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch 3"]:
    """Active rotation of vectors: ``(0, v') = q (0, v) q*``, [T] eq. (23), [S] eq. (5).

    Evaluated as ``v' = v + 2 w (u x v) + 2 u x (u x v)`` with ``q = (w, u)``,
    which equals ``to_matrix(q) @ v``. Assumes ``|q| = 1`` (for a non-unit ``q``
    the result is not a rotation of ``v``; normalise first). ``q`` and ``v``
    broadcast over their batch axes.
    """
    q, v = _checks.arguments(q=(q, "quaternion"), v=(v, "vector"), shared=True)
    return _arrays.compiled_rows(_quaternion.rotate, (1, 1), q, v)


def canonicalize(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 4"]:
    """Pick the representative of ``{q, -q}`` (the same rotation, [T] eq. (30)) with ``w >= 0``.

    Ties on ``w = 0`` (180-degree rotations) are broken by the first non-zero
    of ``x, y, z`` being positive, so the choice is deterministic everywhere.
    The map is piecewise ``+-identity``: its derivative is ``+-I``.
    """
    return _arrays.compiled_rows(_quaternion.canonicalize, (1,), _checks.quat(q))


def random(key: Array, shape: tuple[int, ...] | int = (), dtype: Any = None) -> Float[Array, "*shape 4"]:
    """Rotations drawn uniformly from SO(3) (Haar measure): normalised 4-D Gaussians.

    An isotropic Gaussian in R^4 normalised to S^3 is uniform on S^3, and S^3
    covers SO(3) twice uniformly. ``dtype`` defaults to JAX's default float.

    Called eagerly, one compiled program per shape and dtype (:func:`jaxquat._arrays.compiled`),
    as the other public functions: op by op (until session 55) the first call of a shape took
    690-708 ms and each call after it 1.13-1.19 ms, now 537-573 ms and 0.08-0.09 ms (1000
    rotations, float32, one core of this 2-core CPU, fresh processes, least of 50 repeats). The
    draws are the same; the normalisation's last bit may differ from the op-by-op one's.
    """
    if isinstance(shape, int):
        shape = (shape,)
    dtype = _checks.float_dtype(dtype)
    return _arrays.compiled(_random, key, shape=tuple(shape), dtype=dtype)


def _random(key: Array, *, shape: tuple[int, ...], dtype: Any) -> Array:
    g = jax.random.normal(key, shape + (4,), dtype=dtype)
    return g / jnp.sqrt(_safe.norm_sq(g))[..., None]
