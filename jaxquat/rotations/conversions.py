"""Conversions between unit quaternions and the other rotation parametrisations.

Rotation matrices (act on column vectors, ``v' = R v``), rotation vectors,
axis-angle pairs and modified Rodrigues parameters (MRP). Euler angles live in
:mod:`jaxquat.rotations.euler_angles`.

Source documents: Tasora (2016) [T], Chou (1992) [C], Schwab (2002) [S].
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rotation, _safe, _trig

__all__ = [
    "to_matrix",
    "from_matrix",
    "to_rotvec",
    "from_rotvec",
    "to_axis_angle",
    "from_axis_angle",
    "to_mrp",
    "from_mrp",
]


def to_matrix(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrix ``R(q)`` with ``rotate(q, v) == R @ v``.

    ``R = I + 2 w [u]x + 2 [u]x^2`` for ``q = (w, u)``, i.e. [T] eq. (27a),
    [C] eq. (35), [S] eq. (7), written with ``w^2 + |u|^2 = 1`` substituted on
    the diagonal. Assumes ``|q| = 1``: for a non-unit ``q`` the result is not
    orthogonal (normalise first). ``to_matrix(q) == to_matrix(-q)``.
    """
    return _arrays.compiled_rows(_rotation.to_matrix, (1,), _checks.quat(q))


def from_matrix(m: Float[ArrayLike, "*batch 3 3"], *, nearest: bool = False) -> Float[Array, "*batch 4"]:
    """Unit quaternion of a rotation matrix, canonical sign (``w >= 0``).

    Every column of the symmetric matrix ``K = 4 q q^T`` is a linear function of
    ``R`` (diagonal ``1 + R00 + R11 + R22``, ``1 + R00 - R11 - R22``, ...;
    off-diagonal ``R21 - R12``, ``R01 + R10``, ...), so any column is
    proportional to ``q``. As in Shepperd's method ([T] Algorithm 1) one column
    is taken and normalised, one whose diagonal entry is at least 1, chosen by
    three comparisons (Day 2015: ``R22 < 0``, then ``R00 > R11``, else
    ``R00 < -R11``) rather than Shepperd's largest entry; that entry is at least 1
    for every matrix, so the result and its gradient are finite for every
    rotation, including 180-degree ones.

    Matrices that are not exactly orthonormal: by default the result is the
    normalised column, a unit quaternion whose angle from the nearest
    rotation grows linearly with the deviation: about ``0.2 |M^T M - I|_F`` (median
    over random perturbations of size 1e-5 to 1e-2; it is not second order). With
    ``nearest=True`` the result is the eigenvector of ``K`` with the largest
    eigenvalue (Bar-Itzhack 2000), the rotation closest to ``M`` in the
    Frobenius norm (the polar factor's quaternion, to rounding), at the cost of
    a 4x4 eigendecomposition per matrix (``eigh``; on CPU, for 1024 matrices or
    more, Jacobi rotations over the batch). Neither raises on
    a reflection or a singular matrix: validate ``det(M) > 0`` yourself if needed.

    Gradients: both methods are smooth along SO(3). Off SO(3) the default
    result depends on which column was selected, so on the boundary between two
    cases (``R22 = 0``, ``R00 = R11``, ``R00 = -R11``) its derivative in a
    direction leaving SO(3) depends on the branch; the ``nearest=True`` result is
    smooth in every direction (its eigenvector's derivative needs only the top
    eigenvalue to be simple).

    Speed (10^6 matrices, one core of a 2-core EPYC, CPU): 4.0 ms in float32 and
    7.2 ms in float64, against jaxlie's ``SO3.from_matrix`` at 3.5 and 6.6 ms (which
    neither normalises a column off SO(3) nor fixes the sign).
    """
    return _arrays.compiled_rows(_from_matrix, (2,), _checks.mat3(m, "m"), nearest=bool(nearest))


def _from_matrix(m: Array, nearest: bool) -> Array:
    return _rotation.top_eigenvector(_rotation.k_matrix(m)) if nearest else _rotation.from_matrix_shepperd(m)


def to_rotvec(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """Rotation vector ``phi u`` with ``phi`` in ``[0, pi]``.

    ``2 atan2(|v|, |w|) sign(w) v / |v|`` for ``q = (w, v)``: the inverse of
    [T] eq. (31) and twice the vector part of ``log(canonicalize(q))``.
    Scale-invariant, so any non-zero ``q`` is accepted. The factor
    ``atan2(|v|, w)/|v|`` is a series near the identity, so the Jacobian there
    is exactly ``2 I`` on the vector part and all higher derivatives are right.
    At exactly 180 degrees ``phi u`` and ``-phi u`` are the same rotation; the
    sign follows :func:`jaxquat.canonicalize`.
    """
    return _arrays.compiled_rows(_rotation.to_rotvec, (1,), _checks.quat(q), rescale=True)


def from_rotvec(r: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion of the rotation vector ``r = phi u``: ``(cos(phi/2), sin(phi/2) u)``.

    [T] eq. (31), [S] eq. (9); equal to ``exp((0, r/2))``. Smooth at ``r = 0``
    (Jacobian ``I/2`` on the vector part). Any ``|r|`` is accepted; angles beyond
    ``pi`` give ``w < 0``.
    """
    return _arrays.compiled_rows(_rotation.from_rotvec, (1,), _checks.vec3(r, "r"))


def to_axis_angle(q: Float[ArrayLike, "*batch 4"]) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch"]]:
    """Unit axis ``u`` and angle ``phi`` in ``[0, pi]``, [T] eq. (32).

    Computed as ``phi = 2 atan2(|v|, |w|)`` (not ``2 acos(w)``, which loses half
    the digits near the identity) and ``u = sign(w) v/|v|``. Scale-invariant.
    At the identity the axis is undefined: the result is ``u = (1, 0, 0)``,
    ``phi = 0``, with zero gradient for ``u`` and a zero subgradient for ``phi``
    (whose true derivative there does not exist: ``phi = 2|v|`` is a cone).
    """
    return _arrays.compiled_rows(_to_axis_angle, (1,), _checks.quat(q))


def _to_axis_angle(q: Array) -> tuple[Array, Array]:
    w, x, y, z = _canonical_components(q)
    n = _safe.safe_sqrt(x * x + y * y + z * z)
    angle = 2.0 * _trig.atan2(n, w)
    zero = n == 0
    inv = 1.0 / jnp.where(zero, 1.0, n)
    axis = [jnp.where(zero, e, inv * c) for e, c in zip((1.0, 0.0, 0.0), (x, y, z))]
    return _arrays.assemble(*axis), angle


def from_axis_angle(
    axis: Float[ArrayLike, "*#batch 3"], angle: Float[ArrayLike, "*#batch"] | float
) -> Float[Array, "*batch 4"]:
    """Unit quaternion ``(cos(phi/2), sin(phi/2) u)`` of a rotation by ``phi`` about ``u``, [T] eq. (31).

    The axis is normalised here (so any non-zero axis is accepted); a zero axis
    gives the identity when ``phi = 0`` and a quaternion of four NaNs otherwise (there
    is no rotation to return; under ``jit`` as well, so the rest of a batch is kept).
    ``axis`` and ``angle`` broadcast over their batch axes.
    """
    axis, angle = _checks.arguments(axis=(axis, "vector"), angle=(angle, "scalar"), shared=True)
    return _arrays.compiled_rows_broadcast(_from_axis_angle, (1, 0), axis, angle)


def _from_axis_angle(axis: Array, angle: Array) -> Array:
    nsq = _safe.norm_sq(axis)
    unit = axis / jnp.sqrt(jnp.where(nsq > 0, nsq, 1.0))[..., None]
    half = 0.5 * angle
    s, c = _trig.sincos(half)
    return jnp.where(((nsq == 0) & (angle != 0))[..., None], jnp.nan, _quaternion.scalar_vector(c, unit, s))


def to_mrp(q: Float[ArrayLike, "*batch 4"]) -> Float[Array, "*batch 3"]:
    """Modified Rodrigues parameters ``p = v / (|q| + w) = tan(phi/4) u``, with ``|p| <= 1``.

    ``q`` is first put in the ``w >= 0`` hemisphere, so the shadow set is never
    returned and ``|p| <= 1`` (``|p| = 1`` exactly at 180 degrees). Dividing by
    ``|q| + w`` instead of ``1 + w`` makes it scale-invariant. Smooth everywhere
    except the 180-degree hemisphere switch.
    """
    return _arrays.compiled_rows(_to_mrp, (1,), _checks.quat(q))


def _canonical_components(q: Array) -> list[Array]:
    """The components of ``canonicalize(rescaled(q))`` (:func:`jaxquat._arrays.components`)."""
    c = _safe.rescaled_components(*_arrays.components(q))
    sign = _quaternion.canonical_sign(*c)
    return [sign * x for x in c]


# to_mrp, from_mrp and to_axis_angle are written on components (in by _arrays.components, out by
# _arrays.assemble). Session 52 repeated their per-row divisors along the rows (per_row): the
# broadcast's cotangent was a YNNPACK sum over the minor axis on CPU (10^5, one core, gradient
# float32 to_mrp 4.5 -> 0.8 ms, to_axis_angle 4.3 -> 2.2 ms). Session 53, rows -> components,
# measured against session 52's code the same day (10^5, one pinned core, least of 7), value /
# gradient in ms, float32 then float64: to_mrp 1.6 / 2.1 -> 0.6 / 0.83 and 1.8 / 4.3 -> 1.05 /
# 1.86; to_axis_angle 0.97 / 3.3 -> 0.93 / 0.93 and 1.75 / 4.9 -> 1.9 / 2.1; from_mrp 0.34 /
# 1.34 -> 0.26 / 0.38 and 0.62 / 2.67 -> 0.55 / 0.81.


def _to_mrp(q: Array) -> Array:
    w, x, y, z = _canonical_components(q)
    scale = 1.0 / (jnp.sqrt(w * w + x * x + y * y + z * z) + w)
    return _arrays.assemble(scale * x, scale * y, scale * z)


def from_mrp(p: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 4"]:
    """Unit quaternion of modified Rodrigues parameters: ``((1 - |p|^2), 2 p) / (1 + |p|^2)``.

    Any ``p`` is accepted (``|p| > 1`` is the shadow set, giving ``w < 0``). Smooth everywhere.
    """
    return _arrays.compiled_rows(_from_mrp, (1,), _checks.vec3(p, "p"))


def _from_mrp(p: Array) -> Array:
    x, y, z = _arrays.components(p)
    psq = x * x + y * y + z * z
    denom = 1.0 + psq
    scale = 2.0 / denom
    return _arrays.assemble((1.0 - psq) / denom, scale * x, scale * y, scale * z)
