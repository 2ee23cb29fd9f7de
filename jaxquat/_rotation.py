"""Rotation kernels: the maps between quaternions and rotation vectors and matrices,
Davenport's K matrix and its top eigenvector, the right Jacobians of the exponential, slerp
and the sign alignment of key sequences, and the minimal rotation between two directions, on
arrays already validated and broadcast.

The public functions of :mod:`jaxquat.rotations.conversions`, :mod:`jaxquat.manifold.lie`,
:mod:`jaxquat.manifold.interpolate` and :mod:`jaxquat.rotations.geometry` check their arguments and call these;
the rest of the package calls them directly. Plain names: the module is private to the
package (see :mod:`jaxquat._quaternion`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from jax import Array, lax

from . import _arrays, _derivatives, _fusion, _jacobi, _quaternion, _safe, _trig


def to_matrix(q: Array) -> Array:
    """``R(q) = I + 2 w [u]x + 2 [u]x^2`` for unit ``q = (w, u)``, the diagonal written with ``|q| = 1``."""
    rows = matrix_parts([q[..., 0], q[..., 1], q[..., 2], q[..., 3]])
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def matrix_parts(q: Sequence[Array]) -> list[list[Array]]:
    """:func:`to_matrix`'s rows as lists of entries, from ``q``'s four components."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [
        [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
        [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
        [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
    ]


def _k_entries(b: Array | list[Array], shift: float):
    """Entries of Davenport's symmetric 4x4 ``K(B) = [[tr B, z^T], [z, B + B^T - tr(B) I]]`` plus ``shift * I``.

    ``z = (B21 - B12, B02 - B20, B10 - B01)``. For every quaternion
    ``q^T K(B) q = sum_ij B_ij R(q)_ij``; for a rotation matrix ``R`` itself,
    ``K(R) + I = 4 q q^T`` (Bar-Itzhack 2000), so every column of it is
    proportional to ``q``. ``b`` is ``(..., 3, 3)`` or its nine entries row by row.
    """
    entries = b if isinstance(b, list) else _matrix_entries(b)
    b00, b01, b02, b10, b11, b12, b20, b21, b22 = entries
    diag = (
        shift + b00 + b11 + b22,
        shift + b00 - b11 - b22,
        shift - b00 + b11 - b22,
        shift - b00 - b11 + b22,
    )
    off = (b21 - b12, b02 - b20, b10 - b01, b01 + b10, b02 + b20, b12 + b21)
    return diag, off


def _matrix_entries(m: Array) -> list[Array]:
    """The nine entries of ``m`` ``(..., 3, 3)``, row by row."""
    return [m[..., i, j] for i in range(3) for j in range(3)]


def _k_columns(diag, off):
    d0, d1, d2, d3 = diag
    k01, k02, k03, k12, k13, k23 = off
    return [
        (d0, k01, k02, k03),
        (k01, d1, k12, k13),
        (k02, k12, d2, k23),
        (k03, k13, k23, d3),
    ]


def k_matrix(b: Array, shift: float = 0.0) -> Array:
    """Davenport's symmetric 4x4 ``K(B)`` (plus ``shift * I``), built from its columns."""
    cols = _k_columns(*_k_entries(b, shift))
    return jnp.stack([jnp.stack(c, axis=-1) for c in cols], axis=-2)


def _top_column(k: Array, top: Array) -> Array:
    """The top eigenvector ``top``, canonical sign; NaN where ``k`` is not finite. LAPACK's ``eigh``
    returns NaN there, but cuSOLVER's (GPU) returned finite vectors for a NaN input (H100,
    jax 0.11.2, session 26): a silent wrong answer, so the NaN is made explicit."""
    finite = jnp.isfinite(k).all(axis=(-2, -1))[..., None]
    return jnp.where(finite, _quaternion.canonicalize(top), jnp.nan)


# From this many 4x4 matrices on, top_eigenvector solves them by Jacobi rotations on CPU.
_JACOBI_FROM = 1024


def _eigenpairs(k: Array) -> tuple[Array, Array, Array, Array]:
    """``(lam, vecs, lam_top, top)``: the eigenvalues ``(..., 4)`` and eigenvectors (columns) of
    symmetric ``k``, the largest eigenvalue and its eigenvector. On CPU, for a batch of at least
    :data:`_JACOBI_FROM` matrices, by Jacobi rotations (:func:`jaxquat._jacobi.eigh4`, in no
    particular order: the top is picked out element-wise); otherwise by ``eigh`` (ascending).
    The rotations' loop compiles longer: the first ``align_vectors`` of 10 pairs took 0.58 s
    against 0.31 s with ``eigh``, its first gradient 0.89 against 0.53 s, the first ``mean`` 0.87
    against 0.53 s (one core of this 2-core EPYC, two fresh processes each), and ``eigh``
    costs about a microsecond per matrix: a batch of 1024 saves about 1 ms per call."""
    if not _trig.is_cpu() or math.prod(k.shape[:-2]) < _JACOBI_FROM:
        lam, vecs = jnp.linalg.eigh(k)
        return lam, vecs, lam[..., -1], vecs[..., :, -1]
    lam, vecs = _jacobi.eigh4(k)
    lam_top, top = lam[..., 0], vecs[..., :, 0]
    for j in range(1, 4):
        better = lam[..., j] > lam_top
        lam_top = jnp.where(better, lam[..., j], lam_top)
        top = jnp.where(better[..., None], vecs[..., :, j], top)
    return lam, vecs, lam_top, top


@jax.custom_jvp
def _top_eigenvector_f(k: Array) -> Array:
    return _top_column(k, _eigenpairs(k)[3])


@_top_eigenvector_f.defjvp
def _top_eigenvector_jvp(primals, tangents):
    # First-order perturbation of a simple eigenvalue's eigenvector:
    #   dv = sum_{j != top} v_j (v_j^T dK v) / (lam_top - lam_j).
    # Only the gaps to the top eigenvalue appear, so the lower eigenvalues may be
    # degenerate (they are, for K of an exact rotation: 3, -1, -1, -1), where
    # eigh's own derivative divides by zero. The sum runs over every column: the top's
    # own gap is 0, which leaves it out.
    (k,), (dk,) = primals, tangents
    lam, vecs, lam_top, top = _eigenpairs(k)
    v = _top_column(k, top)
    sign = jnp.sum(v * top, axis=-1, keepdims=True)
    others = vecs * sign[..., None]
    gaps = lam_top[..., None] - lam
    safe_gaps = jnp.where(gaps > 0, gaps, 1.0)
    coeff = _arrays.einsum("...ij,...ik,...k->...j", others, dk, v)
    coeff = jnp.where(gaps > 0, coeff / safe_gaps, 0.0)
    return v, _arrays.einsum("...ij,...j->...i", others, coeff)


def top_eigenvector(k: Array) -> Array:
    """Canonical unit eigenvector of the largest eigenvalue of symmetric 4x4 ``k``.

    Differentiated by a custom JVP that needs only the top eigenvalue to be
    simple. Solved by Jacobi rotations on CPU for a batch of 1024 or more
    (:mod:`jaxquat._jacobi`), by ``eigh`` otherwise. Half precision (no ``eigh`` for
    it): float16/bfloat16 inputs are solved in float32 and the result cast back."""
    dtype = k.dtype
    if jnp.finfo(dtype).bits < 32:
        k = k.astype(jnp.float32)
    return _top_eigenvector_f(k).astype(dtype)


def _shepperd_column(entries: list[Array]) -> tuple[list[Array], Array]:
    """A column of ``K(R) + I = 4 q q^T`` whose diagonal entry ``t`` is at least 1, and the factor
    that normalises it with the canonical sign, from the nine entries of ``R`` row by row.

    The column is chosen by three comparisons (M. Day, "Converting a rotation matrix to a
    quaternion", Insomniac Games, 2015): ``R22 < 0`` and ``R00 > R11`` (then
    ``t = 1 + R00 - R11 - R22``, both differences positive), ``R22 < 0`` otherwise (``t = 1 - R00
    + R11 - R22``), ``R22 >= 0`` and ``R00 < -R11`` (``t = 1 - R00 - R11 + R22``), else ``t = 1 +
    R00 + R11 + R22``. So ``t >= 1`` for any matrix, the normalisation never divides by a small
    number, and every branch has finite derivatives; on a rotation ``t = 4 q_j^2``, so
    ``|q_j| >= 1/2``, as with the largest diagonal entry (Shepperd's choice, which this replaced:
    its maximum and equality tests made XLA on CPU write the diagonal entries out as arrays of
    their own, and ``from_matrix`` at 10^6 took 7.1 ms in float32 against jaxlie's 3.4 ms, and 40
    ms in float64 against 6.4 ms)."""
    diag, off = _k_entries(entries, 1.0)
    low, first = _day_case(entries)
    columns = zip(*_k_columns(diag, off))
    col = [jnp.where(low, jnp.where(first, c1, c2), jnp.where(first, c3, c0)) for c0, c1, c2, c3 in columns]
    # (lax.rsqrt is a scalar call on CPU)
    return col, _quaternion.canonical_sign(*col) / jnp.sqrt(sum(c * c for c in col))


def _day_case(entries: list[Array]) -> tuple[Array, Array]:
    """Day's comparisons: ``R22 < 0``, and then ``R00 > R11``, else ``R00 < -R11``. The column is
    1 (both true), 2 (the first only), 3 (the second only) or 0."""
    r00, r11, r22 = entries[0], entries[4], entries[8]
    low = r22 < 0
    return low, jnp.where(low, r00 > r11, r00 < -r11)


def _shepperd_rows(m: Array) -> Array:
    """:func:`from_matrix_shepperd`'s value and forward mode: the entries indexed from ``m`` and the
    result's components stacked on a leading axis, moved last at the end (XLA computes it in two
    loops, each component's row contiguous)."""
    col, scale = _shepperd_column(_matrix_entries(m))
    return jnp.moveaxis(jnp.stack(col) * scale[None], 0, -1)


def _shepperd_components(m: Array) -> Array:
    """:func:`from_matrix_shepperd` in components (:func:`_arrays.components` of the nine entries,
    :func:`_arrays.assemble`), as JAX differentiates it off the CPU."""
    col, scale = _shepperd_column(_arrays.components(m.reshape(m.shape[:-2] + (9,))))
    return _arrays.assemble(*(c * scale for c in col))


# Rows of the cotangent computed at a time (_arrays.rows_at_a_time): 2^15 matrices, 1.2 MB of
# float32 temporaries. At 10^6 in float32 (one core, session 53): 25.5 ms in blocks of 15 625 rows,
# 26.4 in blocks of 62 500, 40.0 in blocks of 250 000 (36 MB of temporaries a call, each page
# faulted in). Session 80 (a 2-core Intel Xeon with 2 MiB of L2 per core, 10^6 matrices, the
# cotangent alone with the entries' loop of _shepperd_cotangent_rows, least of 15 interleaved
# calls, `make bench`'s GLIBC_TUNABLES), blocks of 2^13 / 2^15 / 2^17 matrices: float32 on one
# pinned core 13.2 / 15.4 / - ms, on both cores 20.2 / 15.9 / 14.9 ms (XLA splits a long block's
# loop between the threads); float64 on both cores 34.8 / 32.9 / 29.0 ms. 2^15 stays, between the two.
_COTANGENT_ROWS = 2**15

# From this many matrices the cotangent's entries pass through a loop of their own
# (_shepperd_cotangent_rows).
_ENTRIES_LOOP_ROWS = 2**13


def _shepperd_cotangent(m: Array, g: Array) -> Array:
    """The cotangent of :func:`from_matrix_shepperd` at ``m`` ``(..., 3, 3)`` for ``g`` ``(..., 4)``,
    written out: with ``q = s c / |c|`` (``c`` the chosen column, ``s`` its sign), ``c``'s
    cotangent is ``(s / |c|) (g - q (q . g))``; each entry of the column is one entry of ``K + I``,
    a signed sum of entries of ``R``, whose cotangents the nine sums below gather. Computed in
    one loop (the nine arrays), stacked, in blocks of :data:`_COTANGENT_ROWS` matrices. JAX's
    ``vjp`` of the component form took 44-46 ms at 10^6 in float32 (one core), of the row form
    75 ms; this 25-27 ms (session 53); since session 80 (the entries through a loop of their own:
    :func:`_shepperd_cotangent_rows`) 15.4 ms on one core of a 2-core Intel Xeon under ``make
    bench``'s ``GLIBC_TUNABLES``, 18.9 ms before."""
    batch = m.shape[:-2]
    flat_m, flat_g = m.reshape((-1, 3, 3)), jnp.broadcast_to(g, batch + (4,)).reshape((-1, 4))
    return _arrays.rows_at_a_time(_shepperd_cotangent_rows, _COTANGENT_ROWS, flat_m, flat_g).reshape(batch + (3, 3))


def _shepperd_cotangent_rows(m: Array, g: Array) -> Array:
    """:func:`_shepperd_cotangent` on one block. In a block of at least :data:`_ENTRIES_LOOP_ROWS`
    matrices (a batch that long: a block is the whole batch or :data:`_COTANGENT_ROWS` rows of it)
    the nine entries of ``m`` pass through one loop (:func:`jaxquat._fusion.one_loop`) first: read
    where they are used, XLA on CPU copied six of them (those read twice) into arrays of their own,
    a kernel each, strided reads of the whole block six times. Session 80 (10^6 matrices, a 2-core
    Intel Xeon, the cotangent alone in blocks of 2^15 rows, least of 15 interleaved calls, `make
    bench`'s GLIBC_TUNABLES / glibc's defaults): one pinned core float32 18.9 / 26.3 -> 15.4 / 23.4
    ms, float64 53.3 / 62.6 -> 39.7 / 49.1 ms; both cores float32 18.7 / 23.7 -> 15.9 / 20.9 ms,
    float64 36.9 / 46.2 -> 32.9 / 43.5 ms; the same values to the bit. On a small batch the loop is
    one kernel more than it saves: the gradient of ``sum(from_matrix(m) * W)`` on one core (least of
    interleaved calls, loop / without) at 1 matrix 9.7 / 7.7 us in float32 and 9.2 / 7.5 us in
    float64, at 1000 18.2 / 18.6 and 20.3 / 19.6 us, at 4096 42.1 / 45.2 and 54.4 / 52.1 us, at 8192
    77.3 / 82.7 and 123.8 / 131.3 us, at 20 000 184 / 220 and 364 / 407 us.

    For one matrix the nine cotangent entries are stacked as they are, without
    :func:`jaxquat._fusion.one_loop`: at one matrix its loop (a variadic ``reduce``) cost more than
    the kernels it saves. Session 82 (one core of a 2-core AMD EPYC, least of 3000 interleaved calls,
    the gradient of ``sum(from_matrix(m) * [0, 1, 2, 3])``, loop / stack, float32 and float64 alike):
    1 matrix 8.5 / 6.2 us (jaxlie 6.5 us); 8 matrices 8.9 / 13.2 us, 16 14.9 / 13.7 us, 128 14.1 /
    15.2 us, 1000 20.5 / 34.0 us: from 8 matrices on the stack does not win reliably. The gradient of
    ``sum(from_matrix(m))`` at one matrix (the ops table's batch-1 cell) 8.6 -> 5.3 us in float32 against jaxlie's
    5.7 us, 5.6 us in float64 against 6.0 us. Not in ``one_loop`` itself (its CPU lowering the
    identity for one-element arrays, measured in session 82, one core, least of 1500 interleaved
    calls, float32, gradients, loop / identity, the same values to the bit): ``from_matrix`` 9.0 /
    6.2 us, ``to_euler`` 6.6 / 6.0, ``slerp`` 9.5 / 8.8, ``to_rotvec`` 6.8 / 6.1, but one single-pair
    ``align_vectors`` problem in a batch of one 10.0 / 16.3 us (its six-output cotangent split into
    kernels of their own): it needs a rule for which kernels gain."""
    entries = _matrix_entries(m)
    if m.shape[0] >= _ENTRIES_LOOP_ROWS:
        entries = list(_fusion.one_loop(entries))
    col, scale = _shepperd_column(entries)
    q = [c * scale for c in col]
    gk = [g[..., k] for k in range(4)]
    qg = sum(a * b for a, b in zip(q, gk))
    gc = [scale * (b - a * qg) for a, b in zip(q, gk)]
    low, first = _day_case(entries)
    chosen = [~low & ~first, low & first, low & ~first, ~low & first]  # the column's index, 0 to 3
    zero = jnp.zeros_like(entries[0])
    d = [jnp.where(chosen[a], gc[a], zero) for a in range(4)]  # K's diagonal

    def k(a: int, b: int) -> Array:  # K's entry (a, b), a < b: in column a as row b, in column b as row a
        return jnp.where(chosen[a], gc[b], jnp.where(chosen[b], gc[a], zero))

    k01, k02, k03, k12, k13, k23 = k(0, 1), k(0, 2), k(0, 3), k(1, 2), k(1, 3), k(2, 3)
    ct = [
        d[0] + d[1] - d[2] - d[3],
        k12 - k03,
        k02 + k13,
        k03 + k12,
        d[0] - d[1] + d[2] - d[3],
        k23 - k01,
        k13 - k02,
        k01 + k23,
        d[0] - d[1] - d[2] + d[3],
    ]
    if m.shape[0] == 1:  # one matrix: the loop is the slower kernel (see above)
        return jnp.stack(ct, axis=-1).reshape(m.shape)
    return _arrays.stack_in_one_loop(ct).reshape(m.shape)


def from_matrix_shepperd(m: Array) -> Array:
    """The unit quaternion of ``R`` from a column of ``K(R) + I = 4 q q^T`` (:func:`_shepperd_column`),
    canonical sign.

    Written for each mode on CPU (:func:`_derivatives.forward_and_reverse`): the value and forward
    mode by :func:`_shepperd_rows`, reverse mode by :func:`_shepperd_cotangent`; elsewhere
    :func:`_shepperd_components`, differentiated by JAX. At 10^6 (one core of this 2-core EPYC,
    least of 9 runs, three processes; before: Shepperd's column in components for all three): the
    value 7.1 -> 4.0 ms in float32 and 40 -> 7.2 ms in float64 (jaxlie 3.5 and 6.6 ms), one
    ``jvp`` 39 -> 7.6-8.2 and 77 -> 14-28 ms, the gradient of ``sum(f(m) * W)`` 47 -> 23-27 and
    97 -> 41-48 ms. Session 80 (a 2-core Intel Xeon, ``make bench``'s ``GLIBC_TUNABLES``, least of
    15, two processes each, alternated; the entries' loop of :func:`_shepperd_cotangent_rows`):
    that gradient on one pinned core 21.8-24.0 -> 18.4-20.6 ms in float32 and 56.2-59.3 -> 42.5-44.1
    ms in float64, on both cores 17.5-18.5 -> 14.6-17.4 ms and 35.5-37.5 -> 32.9-33.6 ms; at 1 and
    1000 matrices unchanged (the same program)."""
    return _derivatives.forward_and_reverse(_shepperd_rows, _shepperd_cotangent, _shepperd_components)(m)


def _to_rotvec(q: Array, rescale: bool = False) -> Array:
    """The shortest rotation vector ``2 atan2(|v|, |w|) sign(w) v / |v|`` of ``q = (w, v)``
    (series near the identity); with ``rescale``, of :func:`_safe.rescaled` ``q`` (any
    non-zero scale).

    In components (:func:`_arrays.components`, :func:`_arrays.assemble`). ``to_rotvec`` is this
    kernel with its tangent and cotangent as one-loop kernels on CPU
    (:func:`_derivatives.derivatives_in_one_loop`; elsewhere JAX differentiates it through the
    custom JVP of :func:`_safe.atan2_over_n`). At 10^6 (one core of this 2-core EPYC, least of
    9 runs, three processes each) the gradient of ``sum(f(q))`` took 5.9-6.0 against 26.2-29.6 ms
    in float32 and 16.7-29.8 against 53-66 ms in float64, one ``jvp`` 5.3-5.4 against 6.1-6.5 and
    23-24 against 34-35 ms. Its value stays this kernel's (as a kernel too, 4.4-4.5 against
    4.1-4.2 ms in float32). The table in ``docs/benchmarks.md`` has the times against the row form
    this kernel replaced.

    With ``rescale`` (the public :func:`jaxquat.to_rotvec`) the factor ``2 atan2(|v|, |w|) / |v|``
    is stored together with ``q`` (one :func:`_arrays.scalars` barrier on both) and the assembly takes the
    components from ``q`` again: XLA otherwise kept the four scaled, sign-fixed components as
    arrays of their own until the end. At 10^6 (this 2-core CPU, fresh processes, minimum of 9
    runs, three processes each) the value took 2.4-2.5 against 3.5-11.4 ms in float32 and
    6.0-6.6 against 18.5-25.6 ms in float64 (XLA's temporaries 26 against 50 MB), one ``jvp``
    18-21 against 25-26 ms and 36-40 against 44-49 ms; the gradient unchanged (15-16 and
    32-34 ms); values bit-identical, gradients to rounding (2e-16 in float64, 1.1e-7 in float32)."""

    def canonical(q):
        w, x, y, z = _arrays.components(q)
        if rescale:
            w, x, y, z = _safe.rescaled_components(w, x, y, z)
        sign = _quaternion.canonical_sign(w, x, y, z)
        return sign * w, sign * x, sign * y, sign * z  # as canonicalize, to the bit

    w, x, y, z = canonical(q)
    f2 = 2.0 * _safe.atan2_over_n(x * x + y * y + z * z, w)
    if rescale:
        f2, q = _arrays.scalars(f2, q)  # q's copy is not identified with q: its components are taken again
        _, x, y, z = canonical(q)
    return _arrays.assemble(f2 * x, f2 * y, f2 * z)


to_rotvec = _derivatives.derivatives_in_one_loop(_to_rotvec, core=(1,), out_core=1, value_in_one_loop=False)


def from_rotvec(r: Array) -> Array:
    """``(cos(|r|/2), sin(|r|/2) r / |r|)`` (series near ``r = 0``).

    In components (:func:`_arrays.components`, :func:`_arrays.assemble`), differentiated by
    JAX with the custom JVP of :func:`_safe.sinc_cos_of_sq`."""
    return _arrays.assemble(*exp_components(_arrays.components(r)))


# exp_components' ways of choosing between the series and the direct branch (_safe has each; the third,
# "derivatives by batch", is _exp_derivatives_by_batch)
_SINC_COS = {
    "per element": _safe.sinc_cos_of_sq,
    "by batch": _safe.sinc_cos_of_sq_small_batch,
}


def exp_components(r: Sequence[Array], branches: str = "per element") -> list[Array]:
    """The components of ``Exp(r) = (cos(|r|/2), sin(|r|/2) r / |r|)`` from those of ``r`` (the
    series near ``r = 0``), for kernels written on components (:func:`from_rotvec`, the integrator
    steps, the torque-free flow's steady rotation). ``branches``: ``"per element"``, both branches
    selected element by element (:func:`_safe.sinc_cos_of_sq`); for arguments nearly always
    below the series' switch, ``"derivatives by batch"`` (the derivatives take the series alone
    when the whole batch can: :func:`_exp_derivatives_by_batch`) or ``"by batch"`` (the
    value as well: :func:`_safe.sinc_cos_of_sq_small_batch`). The same values in every way."""
    if branches == "derivatives by batch":
        return list(_exp_derivatives_by_batch(*r))
    r0, r1, r2 = r
    s = 0.25 * (r0 * r0 + r1 * r1 + r2 * r2)  # (phi/2)^2
    sinc, cos = _SINC_COS[branches](s)
    h = 0.5 * sinc
    return [cos, h * r0, h * r1, h * r2]


@jax.custom_jvp
def _exp_derivatives_by_batch(r0: Array, r1: Array, r2: Array) -> tuple[Array, Array, Array, Array]:
    """:func:`exp_components` with ``"derivatives by batch"``: the value ``"per element"`` (fused
    with the rest of a step), the derivatives chosen by the whole batch (:func:`_safe.parts_by_batch`).

    Its JVP rule computes ``r`` and ``s = |r|^2 / 4`` in one loop
    (:func:`jaxquat._fusion.one_loop`), whose ``s`` is the cond's test and operand and whose ``r``
    the loops after the cond read. Before session 75 the rule was that of a function of ``s``
    alone (``_safe.sinc_cos_of_sq_mostly_small``, unused since then and removed in session 78):
    the loop that made ``s`` for the test (in an RKMK4 step, the last stage and the combination
    of the stages, 121 HLO operations) was evaluated again inside the step's
    last loop for ``r`` (the ``jvp``'s step 1597 -> 1547 operations in its loops). Measured on
    ``simulate``'s scan path (1000 bodies x 1000 RKMK4 steps, one pinned core of a 2-core Intel
    Xeon, least of 31, four processes each, alternated), before -> after: torque-free float32
    gradient 24.1-24.9 -> 22.9-23.7 ms, one ``jvp`` 12.9-14.0 -> 12.6-13.0 ms; float64 53.6-55.8
    -> 48.7-49.9 ms and 24.8-25.7 -> 23.9-24.2 ms; with a PD torque, float32, 71.8-75.3 -> 66.3-70.6
    ms and 30.7-31.4 -> 30.3-31.1 ms; the forward pass the same program. The tangents and
    gradients differ from the earlier rule's by rounding (``ds`` written ``r . dr / 2``)."""
    cos, x, y, z = exp_components((r0, r1, r2), "per element")
    return cos, x, y, z


@_exp_derivatives_by_batch.defjvp
def _exp_derivatives_by_batch_jvp(primals, tangents):
    r0, r1, r2 = jnp.broadcast_arrays(*primals)
    d0, d1, d2 = tangents
    s = 0.25 * (r0 * r0 + r1 * r1 + r2 * r2)
    if not _safe.split_across_devices(s):
        r0, r1, r2, s = _fusion.one_loop([r0, r1, r2, s])
    sinc, cos, d_sinc = _safe.parts_by_batch(s)
    ds = 0.5 * (r0 * d0 + r1 * d1 + r2 * d2)
    h = 0.5 * sinc
    dh = 0.5 * d_sinc * ds
    return (cos, h * r0, h * r1, h * r2), (-0.5 * sinc * ds, dh * r0 + h * d0, dh * r1 + h * d1, dh * r2 + h * d2)


def _jacobian(phi: Array, linear: float | Array, quadratic: Array) -> Array:
    """``I + linear * hat(phi) + quadratic * hat(phi)^2`` (coefficients per batch element), written
    out entry by entry with ``hat(phi)^2 = phi phi^T - |phi|^2 I``.

    Before session 52 it was formed from ``hat(phi)`` with a batched 3x3 matrix product for the
    square. Written out, XLA on CPU fused the coefficients (series or trigonometry) into each of
    the nine entries and evaluated them nine times (float64 ``right_jacobian`` 2.1 -> 8.0 ms), so
    they pass through a product with the identity first, which XLA does not fuse (a
    ``jaxquat._fusion.one_loop`` was 40 % faster still, but XLA constant-folds its ``reduce`` when
    every input is a constant: 0.5 s of compiling for 10^5 constant vectors, against 0.08 s with
    the product). 10^5 vectors
    (one core of this 2-core EPYC, least of 15, two processes each; the gradient of
    ``sum(J(phi) * W)``), before -> after: ``right_jacobian`` float32 1.7 -> 0.6 ms, gradient 4.7 ->
    1.4 ms; float64 2.1 -> 1.0 ms and 21.4 -> 5.2 ms; ``right_jacobian_inverse`` float32 1.5 ->
    0.5 ms and 4.4 -> 1.2 ms, float64 1.8 -> 0.75 ms and 18.3 -> 4.3 ms."""
    x, y, z = _arrays.components(phi)
    lin = jnp.broadcast_to(jnp.asarray(linear, phi.dtype), x.shape)
    coef = _arrays.matmul(jnp.stack([lin, jnp.broadcast_to(quadratic, x.shape)], axis=-1), jnp.eye(2, dtype=phi.dtype))
    lin, quad = coef[..., 0], coef[..., 1]
    sq = x * x + y * y + z * z
    rows = [
        [1.0 + quad * (x * x - sq), quad * (x * y) - lin * z, quad * (x * z) + lin * y],
        [quad * (y * x) + lin * z, 1.0 + quad * (y * y - sq), quad * (y * z) - lin * x],
        [quad * (z * x) - lin * y, quad * (z * y) + lin * x, 1.0 + quad * (z * z - sq)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def right_jacobian(phi: Array) -> Array:
    """``J_r(phi) = I - (1 - cos t)/t^2 hat(phi) + (t - sin t)/t^3 hat(phi)^2``, ``t = |phi|``."""
    s = _safe.norm_sq(phi)
    return _jacobian(phi, -_safe.one_minus_cos_over_sq(s), _safe.x_minus_sin_over_cube(s))


def right_jacobian_inverse(phi: Array) -> Array:
    """``J_r(phi)^-1 = I + hat(phi)/2 + (1/t^2 - (1 + cos t)/(2 t sin t)) hat(phi)^2``, ``t = |phi|``."""
    s = _safe.norm_sq(phi)
    return _jacobian(phi, 0.5, _safe.jacobian_inverse_coeff(s))


def _slerp(p: Array, q: Array, t: Array) -> Array:
    """``p (p* q)^t`` along the shorter arc (``q`` flipped when ``p . q < 0``), as
    ``p exp(t log(p* q))``.

    In components (:func:`_arrays.components`, :func:`_quaternion.multiply_components`,
    :func:`_arrays.assemble`). ``slerp`` is this kernel with its value, tangent and cotangent as
    one-loop kernels on CPU (:func:`_derivatives.derivatives_in_one_loop`; elsewhere JAX
    differentiates it with the custom JVPs of :func:`_safe.atan2_over_n` and
    :func:`_safe.sinc_cos_of_sq`). At 10^6 (one core of this 2-core EPYC, least of 9 runs, three
    processes each, float32 / float64): the gradient of ``sum(slerp(p, q, t))`` in ``p`` 11.8 /
    38-42 against 42-46 / 89-108 ms, one ``jvp`` 11.7 / 40-41 against 31-35 / 70-85 ms, the value
    9.7-10.1 / 37-46 against 9.9-10.7 / 49-63 ms."""
    pc = _arrays.components(p)
    qc = _arrays.components(q)
    flip = jnp.where(pc[0] * qc[0] + pc[1] * qc[1] + pc[2] * qc[2] + pc[3] * qc[3] < 0, -1.0, 1.0).astype(p.dtype)
    qc = [flip * c for c in qc]
    w, x, y, z = _quaternion.multiply_dense([pc[0], -pc[1], -pc[2], -pc[3]], qc)
    nsq = x * x + y * y + z * z
    scale = t * _safe.atan2_over_n(nsq, w)  # t * (half angle) / |v|
    sinc, cos = _safe.sinc_cos_of_sq(scale * scale * nsq)
    k = scale * sinc
    return _arrays.assemble(*_quaternion.multiply_dense(pc, [cos, k * x, k * y, k * z]))


slerp = _derivatives.derivatives_in_one_loop(_slerp, core=(1, 1, 0), out_core=1)


def align_signs(keys: Array) -> Array:
    """Flip keys ``(..., n, 4)`` so that consecutive ones have a non-negative dot product."""
    dots = jnp.sum(keys[..., 1:, :] * keys[..., :-1, :], axis=-1)
    steps = jnp.where(dots < 0, -1.0, 1.0).astype(keys.dtype)
    # The running product by lax.associative_scan (products of shifted slices), not jnp.cumprod: on
    # CPU a reduce-window, which XLA evaluated while compiling when the keys were constants of
    # the program (10^5 x 5 keys: 1.5 s); the same values, and 4.0 against 4.3 ms at run time.
    ends = lax.associative_scan(jnp.multiply, steps, axis=-1)
    signs = jnp.concatenate([jnp.ones_like(steps[..., :1]), ends], axis=-1)
    return keys * signs[..., None]


def _minimal_rotation(a: Array, b: Array) -> Array:
    """Smallest rotation taking the direction of ``b`` onto that of ``a``: ``(|a||b| + a.b, b x a)``
    normalised (Horn's closed form), its first component written ``|b x a|^2 / (|a||b| - a.b)``
    where ``a.b < 0`` (the sum cancels there); where ``a`` and ``b`` are antiparallel to within
    ``|b x a| <= sqrt(eps) |a||b|`` the rotation by pi about ``b x e``, ``e`` the first or second
    coordinate axis (whichever is farther from ``b``); canonical sign.

    The threshold balances two errors: the half turn's, the angle ``theta`` between ``-b`` and
    ``a``, and Horn's, whose axis ``b x a`` is computed with an absolute error of order
    ``eps |a||b|`` (about ``0.4 eps / theta`` radians measured). Until session 82 the half turn was
    taken wherever ``|a||b| + a.b <= 1000 eps |a||b|`` (``theta`` up to ``sqrt(2000 eps)``, and
    the sum itself off by a few ``eps |a||b|`` near there): the largest angle between ``R(q) b`` and
    ``a`` over pairs 1e-7 to 0.3 rad from antiparallel (20 000 pairs at each of 40 angles, the
    vectors' lengths 0.14 to 7.4, against float64 with the same rounded inputs) was 1.5e-2 rad in
    float32 and 4.1e-7 in float64; now 3.2e-4 and 1.2e-8.

    In components (:func:`_arrays.components`, :func:`_arrays.assemble`): ``minimal_rotation`` is
    this kernel with its value, tangent and cotangent as one-loop kernels on CPU
    (:func:`_derivatives.derivatives_in_one_loop`). Until session 82 it was written on rows
    (``jnp.cross``, ``jnp.where`` of rows, a row normalisation). One core of a 2-core AMD EPYC,
    least of 2000 (12) interleaved calls, float32 / float64, before -> after: the gradient of a single
    pair's ``align_vectors`` (``jax.grad`` of ``sum(align_vectors(v, rotate(q, v)))`` in ``v``,
    ``docs/benchmarks.md``'s ops table at batch 1) 40 -> 5 kernels, 16.4 / 16.3 -> 9.2 / 9.3 us
    (Horn's formula written plainly in ``jnp``, as brax's ``from_to``: 9.7 / 9.7 us), its value
    7.9 us either way; 10^6 pairs, value 15.0 / 25.5 -> 4.0 / 8.3 ms, gradient in both vectors
    80 / 149 -> 8.0 / 17.2 ms. The first component's obtuse form multiplies by a
    :func:`_trig.reciprocal`: as a :func:`_trig.divide` the gradient at 10^6 took 16 kernels and
    17.0 / 43.0 ms."""
    ax, ay, az = _arrays.components(a)
    bx, by, bz = _arrays.components(b)
    nab = _trig.sqrt(ax * ax + ay * ay + az * az) * _trig.sqrt(bx * bx + by * by + bz * bz)
    dot = ax * bx + ay * by + az * bz
    vx, vy, vz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax  # b x a
    vsq = vx * vx + vy * vy + vz * vz
    obtuse = dot < 0
    # |a||b| + a.b cancels as a and b turn antiparallel; there it is |b x a|^2 / (|a||b| - a.b).
    w = jnp.where(obtuse, vsq * _trig.reciprocal(jnp.where(obtuse, nab - dot, 1.0)), nab + dot)
    anti = obtuse & (vsq <= jnp.finfo(a.dtype).eps * (nab * nab))
    # b x e: e = (1, 0, 0) where |b_x| is not the largest component, else e = (0, 1, 0).
    pick_x = jnp.abs(bx) <= jnp.maximum(jnp.abs(by), jnp.abs(bz))
    zero = jnp.zeros_like(w)
    w = jnp.where(anti, zero, w)
    x = jnp.where(anti, jnp.where(pick_x, zero, -bz), vx)
    y = jnp.where(anti, jnp.where(pick_x, bz, zero), vy)
    z = jnp.where(anti, jnp.where(pick_x, -by, bx), vz)
    r = _trig.reciprocal(_trig.sqrt(w * w + x * x + y * y + z * z))
    w, x, y, z = w * r, x * r, y * r, z * r
    sign = _quaternion.canonical_sign(w, x, y, z)
    return _arrays.assemble(sign * w, sign * x, sign * y, sign * z)


minimal_rotation = _derivatives.derivatives_in_one_loop(_minimal_rotation, core=(1, 1), out_core=1)
