"""Jacobi elliptic functions and Carlson's symmetric elliptic integrals in JAX.

These are what the torque-free rigid body (Euler-Poinsot motion) is made of:
the body angular velocity is ``(cn, sn, dn)`` of a linear function of time and
the precession angle needs the incomplete integral of the third kind. The
functions follow :mod:`scipy.special`'s names and parameter convention
(parameter ``m = k**2``, amplitude ``phi``), work element-wise over any batch
shape, under ``jit``/``vmap`` and both modes of autodiff, in float32 and float64.

Algorithms (fixed iteration counts: ``lax`` loops whose trip count is known when compiling):

* :func:`ellipj` and :func:`ellipk`: the arithmetic-geometric mean (AGM) and the
  descending Landen recurrence (Abramowitz and Stegun 16.4 and 17.6). The
  first AGM step is written ``c_1 = m / (2 (1 + sqrt(1 - m)))`` so the result
  is smooth in ``m`` at ``m = 0`` (where ``sqrt(m)`` is not).
* :func:`elliprf` and :func:`elliprj`: Carlson's duplication theorem with the
  fifth-order series of Carlson (1995), "Numerical computation of real or
  complex elliptic integrals", Numer. Algorithms 10. Both integrals move ``x, y, z`` by the same
  step, so where both are needed of the same arguments (the integral of the third kind)
  :func:`carlson` takes them from one loop. The AGM depends on ``m`` alone: :func:`am_given`
  takes it formed once for many ``u`` (the torque-free flow's times).

Iteration counts: the AGM converges quadratically once ``a`` and ``b`` are
within a factor of two; starting from ``b_0 = sqrt(1 - m)`` as small as the
smallest normal float it needs about 14 steps, and 20 are taken. The duplication
step shrinks the spread of the arguments by 4 and the series is of order 6 in
it, so 14 steps reach float64 rounding from arguments that differ by 300 orders
of magnitude.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _fusion, _trig

__all__ = ["ellipj", "ellipk", "elliprf", "elliprj"]

_AGM_STEPS = 20
_DUPLICATION_STEPS = 16


def tiny(x: Array) -> Array:
    return jnp.asarray(jnp.finfo(x.dtype).tiny, x.dtype)


def tiny_cos(x: Array) -> Array:
    """The ``c`` the complete integrals pass :func:`legendre` (``x = c^2`` the smallest normal float
    in ``x``'s dtype, to rounding, for 0: :func:`complete_y` has why)."""
    return jnp.sqrt(tiny(x))


def agm(m: Array, mc: Array) -> tuple[tuple[Array, Array, Array], Array]:
    """``(a_n, b_n, c_n)`` for ``n = 1..N`` (each stacked on a new leading axis) of the AGM of
    ``(1, sqrt(mc))``, and ``a_N``.

    ``c_{n+1} = c_n^2 / (4 a_{n+1})`` (``c = (a - b) / 2`` without cancellation), from ``c_0^2 = m``.
    One scan writes the three sequences (stacking a first step formed apart took five more XLA
    kernels, each compiled on its own)."""
    b0 = jnp.sqrt(jnp.maximum(mc, tiny(mc)))

    def step(abc, _):
        a, b, c2 = abc  # c2 = c_n^2
        a_next = (a + b) / 2
        b_next, c_next = _fusion.fusible(jnp.sqrt(a * b)), _fusion.fusible(c2 / (4 * a_next))
        return (a_next, b_next, c_next * c_next), (a_next, b_next, c_next)

    start = jnp.broadcast_arrays(jnp.ones_like(b0), b0, m)
    _, steps = lax.scan(step, tuple(_fusion.one_loop(start)), None, length=_AGM_STEPS)
    return steps, steps[0][-1]


def amplitude(u: Array, steps: tuple[Array, Array, Array], a_last: Array) -> Array:
    """The Jacobi amplitude ``am(u | m)`` (unwrapped: it grows with ``u``) by the Landen recurrence.

    The textbook step ``phi <- (phi + asin((c_n/a_n) sin phi)) / 2`` loses half the
    digits near the separatrix (``c_n/a_n -> 1``, where ``asin`` is steep); since
    ``a_n^2 - c_n^2 = b_n^2`` it is written as the well-conditioned
    ``atan2(c_n sin phi, hypot(a_n cos phi, b_n sin phi))``.
    """

    def step(phi, abc):
        a, b, c = abc
        s, co = _trig.sincos(phi)
        return (phi + _trig.atan2(c * s, _fusion.fusible(jnp.sqrt((a * co) ** 2 + (b * s) ** 2)))) / 2, None

    phi0 = (2.0**_AGM_STEPS) * a_last * u
    # Rank-aligned, not broadcast: a per-body AGM shared by many u stays per body in the loop's
    # inputs (broadcast, it was stored at the size of u, 8 MB each at 10^5 u in float32).
    abc = tuple(x.reshape((_AGM_STEPS,) + (1,) * (phi0.ndim - x.ndim + 1) + x.shape[1:]) for x in steps)
    order = _shared_axes_first(phi0.shape, abc[0].shape[1:])
    if order is None:
        phi, _ = lax.scan(step, phi0, abc, reverse=True)
        return phi
    abc = tuple(x.transpose((0, *(i + 1 for i in order))) for x in abc)
    phi, _ = lax.scan(step, phi0.transpose(order), abc, reverse=True)
    return phi.transpose(np.argsort(order))


def _shared_axes_first(shape: tuple[int, ...], shared: tuple[int, ...]) -> tuple[int, ...] | None:
    """:func:`amplitude`'s loop axes: those of ``u`` (``shape``) along which the AGM (``shared``,
    rank-aligned) is shared first, the parameters' own axes last; ``None`` (the order as it is)
    where the shared extent is under 4, a multiple of 16 (whole vectors) or not shorter than the
    rest.

    Why: XLA's CPU loop emitter vectorises along the last axis; a body's AGM shared by its saved
    times (``simulate``'s closed form, ``B`` bodies x ``T`` times) put the times last. The Landen
    loop per element (20 steps, one core of a 2-core AMD EPYC with AVX-512, float32, least of 10,
    session 83), times last -> first: 1000 x 4 52 -> 31 ns, 1000 x 10 81 -> 28, 1000 x 20 49 -> 26,
    1000 x 101 35 -> 26, 10^4 x 10 79 -> 27, 10^5 x 10 81 -> 27; at 2 and 3 times it was as fast
    or faster times last (10^5 x 2: 26 against 29-32 ns, 10^5 x 3: 21 against 59 ns), and so it
    was at a multiple of 16 times, whole vectors of up to 16 lanes (1000 x 16, 32, 64, 128, 256 and
    10^4 x 16, 48: 24.1-25.3 against 24.9-26.4 ns). The closed form's forward pass at 1000 x 10:
    2.2-2.3 -> 1.7 ms (float64 4.8-5.0 -> 4.1 ms), at 1000 x 101 12.0-12.1 -> 11.1-11.2 ms
    (float64 within the spread). The two transposes are copies of ``u``'s size, once."""
    own = [i for i, n in enumerate(shared) if n != 1 or shape[i] == 1]
    times = [i for i in range(len(shape)) if i not in own]
    extent = math.prod(shape[i] for i in times)
    if not times or extent < 4 or extent % 16 == 0 or math.prod(shape[i] for i in own) <= extent:
        return None
    return (*times, *own)


def sn_cn_dn(phi: Array, m: Array, mc: Array) -> tuple[Array, Array, Array]:
    """``sn, cn, dn`` from the amplitude ``phi = am(u | m)``."""
    sn, cn = _trig.sincos(phi)
    return sn, cn, jnp.sqrt(mc + m * cn * cn)  # dn = sqrt(1 - m sn^2), no cancellation near m = 1


def am(u: Array, m: Array, mc: Array) -> Array:
    """The unwrapped amplitude ``am(u | m)``; ``mc = 1 - m`` given separately for accuracy near ``m = 1``.
    (:func:`am_given` with the AGM of ``m`` formed here.)"""
    return am_given(u, m, mc, complete_rd(mc), *lax.stop_gradient(agm(m, mc)))


def complete_rd(mc: Array) -> Array:
    """``R_D(0, 1, 1 - m) = 6 K'(m)`` (with ``tiny`` for the zeros, so ``m = 1`` stays finite), the
    per-parameter input of :func:`am_given`."""
    return rd(tiny(mc) * jnp.ones_like(mc), jnp.ones_like(mc), jnp.maximum(mc, tiny(mc)))


@jax.custom_jvp
def am_given(
    u: Array, m: Array, mc: Array, rd_complete: Array, steps: tuple[Array, Array, Array], a_last: Array
) -> Array:
    """The unwrapped amplitude ``am(u | m)`` from the AGM ``(steps, a_last) = agm(m, mc)`` of its
    parameter and ``rd_complete = complete_rd(mc)``, formed once for many ``u`` (the torque-free
    flow's saved times share one per body). ``rd_complete`` enters the derivative only; formed
    differentiably by the caller, it keeps higher derivatives exact.

    Differentiating the AGM/Landen loop loses the derivative in ``m`` as ``m -> 1``
    (it differentiates ``sqrt(1 - m)``, whose singularity the exact derivative does not
    have) and gives NaN at ``m = 1``. The rule below is the implicit derivative of
    ``u = F(am | m)``: ``d am = dn (du - F_m dm)`` with, for ``am = j pi + r``
    (``|r| <= pi/2``), ``F_m = 2 j K'(m) + sin^3 r R_D(cos^2 r, 1, dn^2) / 6`` and
    ``K'(m) = R_D(0, 1, 1 - m) / 6``. The second term follows from the Carlson form of
    ``E`` (DLMF 19.25.10), which cancels the ``1 / (m (1 - m))`` of the textbook formula
    exactly, so it is regular at ``m = 1`` (and at ``m = 0``). The tangents of ``mc``,
    ``rd_complete`` and the AGM are not used: callers pass ``mc = 1 - m`` analytically and the
    others as functions of ``m``.
    """
    return amplitude(u, steps, a_last)


@am_given.defjvp
def _am_jvp(primals, tangents):
    u, m, mc, rd_complete, *agm_of_m = primals
    du, dm, *_ = tangents
    phi = am_given(u, m, mc, rd_complete, *agm_of_m)
    j = jnp.round(phi / jnp.pi)
    s, c = _trig.sincos(phi - j * jnp.pi)
    dn = jnp.sqrt(jnp.maximum(mc + m * c * c, 0.0))
    f_m = s * s * s * rd(c * c, jnp.ones_like(c), dn * dn) / 6 + jnp.where(j != 0, 2 * j * rd_complete / 6, 0.0)
    return phi, dn * (du - f_m * dm)


def _jacobi(u: Array, m: Array, mc: Array) -> tuple[Array, Array, Array, Array]:
    """``sn, cn, dn, am`` with the complementary parameter ``mc = 1 - m`` given separately."""
    phi = am(u, m, mc)
    return (*sn_cn_dn(phi, m, mc), phi)


def quarter_period(m: Array, mc: Array) -> Array:
    """``K(m) = pi / (2 AGM(1, sqrt(1 - m)))``."""
    _, a_last = agm(m, mc)
    return jnp.pi / (2 * a_last)


def _broadcast(args, names):
    """The arguments validated and broadcast, in the working dtype (float32 for half
    precision), and the dtype the results are cast back to."""
    arrays = _checks.arguments(**{n: (a, "scalar") for a, n in zip(args, names)})
    dtype = arrays[0].dtype
    work = _checks.working_dtype(dtype)
    return [a.astype(work) for a in arrays], dtype


def ellipj(u: Float[ArrayLike, "*#batch"], m: Float[ArrayLike, "*#batch"]) -> tuple[Array, Array, Array, Array]:
    """Jacobi elliptic functions ``sn, cn, dn`` and the amplitude ``am`` of ``u`` with parameter ``m``.

    ``am(u | m) = phi`` inverts ``u = int_0^phi dt / sqrt(1 - m sin^2 t)``;
    ``sn = sin(phi)``, ``cn = cos(phi)``, ``dn = sqrt(1 - m sn^2)``. Defined for
    ``0 <= m <= 1`` (``m = 1`` gives ``tanh, sech, sech``); same order of outputs
    as :func:`scipy.special.ellipj`. ``u`` and ``m`` broadcast together.
    Euler-Poinsot motion: Landau and Lifshitz, Mechanics, section 37.
    """
    (u, m), dtype = _broadcast((u, m), ("u", "m"))
    return tuple(x.astype(dtype) for x in _arrays.compiled_rows(_ellipj, (0, 0), u, m))


# The public functions' kernels are compiled whole: called eagerly they ran operation by
# operation, each compiled for every new shape (tests/test_elliptic.py, float32: 13.0 s, now
# 7.3 s; _arrays.compiled). Inside a user's jit they inline.
def _ellipj(u: Array, m: Array) -> tuple[Array, ...]:
    return tuple(jnp.where(m > 1, jnp.nan, x) for x in _jacobi(u, m, 1 - m))  # as scipy: NaN outside m <= 1


def _ellipk(m: Array) -> Array:
    return jnp.where(m > 1, jnp.nan, quarter_period(m, 1 - m))


def ellipk(m: Float[ArrayLike, "*batch"]) -> Array:
    """Complete elliptic integral of the first kind ``K(m) = int_0^(pi/2) dt / sqrt(1 - m sin^2 t)``.

    Computed as ``pi / (2 AGM(1, sqrt(1 - m)))`` for ``m < 1`` (negative ``m`` included);
    ``K(1) = inf``: here it is finite but huge, about ``ln(4 / sqrt(tiny))``. ``m > 1``
    (where ``K`` is complex) and ``m = inf`` give NaN, as scipy does. Same convention as
    :func:`scipy.special.ellipk`.
    """
    (m,), dtype = _broadcast((m,), ("m",))
    return _arrays.compiled_rows(_ellipk, (0,), m).astype(dtype)


def _duplicate(x: Array, y: Array, z: Array) -> tuple[Array, Array, Array, Array]:
    sx, sy, sz = (_fusion.fusible(jnp.sqrt(v)) for v in (x, y, z))
    return sx, sy, sz, sx * sy + sy * sz + sz * sx


def rf(x: Array, y: Array, z: Array) -> Array:
    def step(_, xyz):
        *_, lam = _duplicate(*xyz)
        return tuple((v + lam) / 4 for v in xyz)

    return _rf_series(*lax.fori_loop(0, _DUPLICATION_STEPS, step, (x, y, z)))


def _rf_series(x: Array, y: Array, z: Array) -> Array:
    """R_F from arguments the duplication has brought together (Carlson's fifth-order series)."""
    a = (x + y + z) / 3
    dx, dy = 1 - x / a, 1 - y / a
    dz = -(dx + dy)
    e2 = dx * dy - dz * dz
    e3 = dx * dy * dz
    return (1 - e2 / 10 + e3 / 14 + e2 * e2 / 24 - 3 * e2 * e3 / 44) / jnp.sqrt(a)


def _rc_one(e: Array) -> Array:
    """``R_C(1, 1 + e)``: ``atan(sqrt(e))/sqrt(e)`` (``e > 0``), ``atanh(sqrt(-e))/sqrt(-e)`` (``e < 0``).

    ``atan`` is :func:`jaxquat._trig.atan2` and ``atanh(r)`` is ``log1p(2 r / (1 - r)) / 2``: XLA on
    CPU evaluates ``jnp.arctan`` and ``jnp.arctanh`` by scalar library calls (float32, 1.6 million
    elements, one core: ``arctan`` 14 ms, ``log1p`` 1.2 ms), and they were most of :func:`carlson`'s
    time (101 000 points: 19 -> 8.4 ms in float32, 33 -> 17 ms in float64). The error on
    ``-0.9 < e < 1`` is 2 ulp in both dtypes (``jnp.arctanh`` had 72 ulp in float64)."""
    small = jnp.abs(e) < 1e-3
    series = 1 - e / 3 + e * e / 5 - e**3 / 7 + e**4 / 9 - e**5 / 11
    t = jnp.sqrt(jnp.where(small, 1.0, jnp.abs(e)))
    r = jnp.where(small | (e > 0), 0.5, t)  # atanh's argument, a safe 0.5 where it is not used
    direct = jnp.where(e > 0, _trig.atan2(t, jnp.ones_like(t)), jnp.log1p(2 * r / (1 - r)) / 2) / t
    return jnp.where(small, series, direct)


def carlson(x: Array, y: Array, z: Array, p: Array) -> tuple[Array, Array]:
    """``(R_F(x, y, z), R_J(x, y, z, p))`` from one duplication loop: both integrals move
    ``x, y, z`` by the same step, so R_F's series is evaluated on R_J's final arguments (one loop
    instead of two where a caller needs both: the incomplete integral of the third kind).

    In reverse mode each step is recomputed from its carry (``jax.checkpoint``) rather than
    storing its dozen intermediates for every step, and the carry's values and cotangents are
    each formed in one loop (:mod:`jaxquat._fusion`). Measured (the gradient of ``Pi(n; r | m)``
    at 101 000 points, one core of this 2-core CPU): 192 -> 68 ms in float32, 337 -> 137 ms in
    float64, against 19 / 37 ms for the value; ``simulate``'s closed form (1000 bodies x 101 times)
    gradient 280 -> 154 ms and 510 -> 283 ms. :func:`legendre` differentiates it in closed form
    instead (:func:`_carlson_unit_z`)."""
    r_f, r_j, *_ = _carlson(x, y, z, p)
    return r_f, r_j


def _carlson(x: Array, y: Array, z: Array, p: Array, c: Array | None = None) -> tuple[Array, ...]:
    """:func:`carlson`'s loop; with ``c`` (``c^2 = x``): also ``c R_D(y, z, x)``,
    ``R_D(z, x, y)`` and ``R_D(x, y, z)`` (each argument in turn the distinguished one), whose sums
    ride on the same duplication steps: each term is ``3 4^-k / (sqrt(v_k) (v_k + lambda_k))``, as
    in :func:`rd`. ``R_D(y, z, x)`` grows as ``1 / sqrt(x)`` at ``x = 0``; scaled by ``c`` its first
    term is ``3 sign(c) / (x + lambda_0)`` (``sign(0) = 1``: ``c >= 0``'s side), finite there."""
    # The loop's inputs and its invariant in one loop (each an XLA kernel of its own otherwise).
    x, y, z, p = jnp.broadcast_arrays(x, y, z, p)
    zero = jnp.zeros_like(x)
    x, y, z, p, zero, delta = _fusion.one_loop_both_ways((x, y, z, p, zero, (p - x) * (p - y) * (p - z)))
    sums = () if c is None else (zero,) * 3
    cs = x if c is None else jnp.broadcast_to(c, x.shape)  # cs and sign_c: read with c given only
    sign_c = x if c is None else jnp.where(cs < 0, -1.0, 1.0).astype(x.dtype)

    @jax.checkpoint
    def step(i, carry):
        x, y, z, p, total, *rd_sums = _fusion.one_loop_backward(carry)
        scale = jnp.asarray(0.25, x.dtype) ** i.astype(x.dtype)
        sx, sy, sz, lam = _duplicate(x, y, z)
        sp = _fusion.fusible(jnp.sqrt(p))
        d = (sp + sx) * (sp + sy) * (sp + sz)
        total = total + _fusion.fusible(scale / d) * _rc_one(_fusion.fusible(delta * scale**3 / (d * d)))
        if rd_sums:  # c / sqrt(x_k): sign(c) at the first step, where sqrt(x_0) = |c|
            c_over_sx = jnp.where(i == 0, sign_c, cs / jnp.where(sx == 0, 1.0, sx))
            scaled = (c_over_sx, 1 / sy, 1 / sz)
            rd_sums = [acc + scale * f / (v + lam) for acc, f, v in zip(rd_sums, scaled, (x, y, z))]
        return _fusion.one_loop_both_ways(((x + lam) / 4, (y + lam) / 4, (z + lam) / 4, (p + lam) / 4, total, *rd_sums))

    carry = lax.fori_loop(0, _DUPLICATION_STEPS, step, (x, y, z, p, zero, *sums))
    x, y, z, p, total, *rd_sums = _fusion.one_loop_backward(carry)
    rds = tuple(3 * acc + f * _rj_tail(x, y, z, v) for acc, f, v in zip(rd_sums, (cs, 1.0, 1.0), (x, y, z)))
    return (_rf_series(x, y, z), 6 * total + _rj_tail(x, y, z, p), *rds)


@jax.custom_jvp
def _carlson_unit_z(c: Array, y: Array, p: Array) -> tuple[Array, Array]:
    """``(R_F(x, y, 1), R_J(x, y, 1, p))`` at ``x = c^2`` (:func:`carlson`), differentiated in
    closed form, for :func:`legendre`.

    The partial derivatives are Carlson integrals again (the integral forms differentiated under
    the sign, then partial fractions): ``dR_F/dv = -R_D_v / 6`` and ``dR_J/dv = (R_J - R_D_v) /
    (2 (p - v))`` for ``v`` in ``x, y, z``, where ``R_D_v`` is ``R_D`` with ``v`` the distinguished
    argument; ``dR_J/dp`` follows from ``R_J``'s homogeneity of degree ``-3/2``:
    ``p dR_J/dp = -3/2 R_J - x dR_J/dx - y dR_J/dy - z dR_J/dz``. The three ``R_D`` come from the
    value's own loop (:func:`_carlson` given ``c``), and the derivatives are element-wise after it:
    reverse mode stores five arrays and transposes products, instead of the loop's carry at
    every step and a second loop run backwards (the loop's gradient cost 6.4x its value: 10^6
    points, float32, this 2-core Intel Xeon).

    In ``c``, not ``x``: ``R_D_x`` grows as ``1 / |c|`` and ``dx/dc = 2 c``, so at ``c = 0`` (an
    amplitude at a quarter turn, as at the start of a body whose rate about the axis ``c`` is 0)
    the derivative in ``x`` was infinite and that in ``c`` ``inf * 0``: NaN, in JAX's
    derivatives through the loop as well (whose ``sqrt(x)`` has an infinite derivative at 0).
    ``c R_D_x`` is formed finite in the loop (:func:`_carlson`).

    ``(R_J - R_D_v) / (p - v)`` is 0/0 at ``p = v`` and loses ``eps / |p - v|`` near it; there it
    is taken as 0. In :func:`legendre` ``R_J`` is multiplied by ``n s^3``, and with ``x = 1 - s^2``,
    ``y = 1 - m s^2``, ``z = 1``, ``p = 1 - n s^2`` the gaps are ``(1 - n) s^2``, ``(m - n) s^2``
    and ``-n s^2``: the lost digits are those of a product with ``s^3`` or ``n`` (the torque-free
    flow has ``n <= 0 <= m``), so the derivatives of ``F`` and ``Pi`` keep their precision."""
    return carlson(c * c, y, jnp.ones_like(c), p)


@_carlson_unit_z.defjvp
def _carlson_unit_z_jvp(primals, tangents):
    c, y, p = jnp.broadcast_arrays(*primals)
    dc, dy, dp = (jnp.broadcast_to(t, c.shape) for t in tangents)
    x, z = c * c, jnp.ones_like(c)
    r_f, r_j, c_rd_x, rd_y, rd_z = _carlson(x, y, z, p, c)

    def gap_ratio(num, gap):  # num / gap, 0 where the gap is 0 (the prefactor n s^3 is 0 there)
        safe = gap != 0
        return jnp.where(safe, num / jnp.where(safe, gap, 1.0), 0.0)

    j_c = gap_ratio(c * r_j - c_rd_x, p - x)  # dR_J/dc = 2 c dR_J/dx
    j_y, j_z = 0.5 * gap_ratio(r_j - rd_y, p - y), 0.5 * gap_ratio(r_j - rd_z, p - z)
    j_p = (-1.5 * r_j - 0.5 * c * j_c - y * j_y - z * j_z) / p
    return (r_f, r_j), (-c_rd_x * dc / 3 - rd_y * dy / 6, j_c * dc + j_y * dy + j_p * dp)


def _rj_tail(x: Array, y: Array, z: Array, p: Array) -> Array:
    """``4^-N R_J`` of the arguments after ``N`` duplication steps (Carlson's fifth-order series)."""
    scale = jnp.asarray(0.25**_DUPLICATION_STEPS, x.dtype)
    a = (x + y + z + 2 * p) / 5
    dx, dy, dz = 1 - x / a, 1 - y / a, 1 - z / a
    dp = -(dx + dy + dz) / 2
    e2 = dx * dy + dx * dz + dy * dz - 3 * dp * dp
    e3 = dx * dy * dz + 2 * e2 * dp + 4 * dp**3
    e4 = (2 * dx * dy * dz + e2 * dp + 3 * dp**3) * dp
    e5 = dx * dy * dz * dp * dp
    series = 1 - 3 * e2 / 14 + e3 / 6 + 9 * e2 * e2 / 88 - 3 * e4 / 22 - 9 * e2 * e3 / 52 + 3 * e5 / 26
    return scale * series / (a * jnp.sqrt(a))


def rd(x: Array, y: Array, z: Array) -> Array:
    """Carlson's ``R_D(x, y, z) = R_J(x, y, z, z)`` by its own duplication loop: with ``p = z`` each
    step's term is ``3 4^-k / (sqrt(z) (z + lambda))``, without :func:`carlson`'s ``R_C`` (an
    ``atan``, an ``atanh`` and a series per step, all evaluated at 0 here). Measured (101 000
    points, one core, float32 / float64): 18.1 / 32.5 ms through :func:`carlson` as it was before
    its ``R_C`` was vectorised, 1.9 / 4.1 ms by this loop."""
    # Flattened: the loop runs over one axis whatever the shape (XLA's CPU loop emitter vectorises
    # along the last axis only; jaxquat._fusion._FLAT_BELOW has the measurements).
    shape = jnp.broadcast_shapes(jnp.shape(x), jnp.shape(y), jnp.shape(z))
    flat = [jnp.broadcast_to(v, shape).reshape(-1) for v in (x, y, z)]
    x, y, z, zero = _fusion.one_loop([*flat, jnp.zeros_like(flat[0])])

    def step(i, carry):
        x, y, z, total = carry
        scale = jnp.asarray(0.25, x.dtype) ** i.astype(x.dtype)
        _, _, sz, lam = _duplicate(x, y, z)
        total = total + scale / (sz * (z + lam))
        return _fusion.one_loop(((x + lam) / 4, (y + lam) / 4, (z + lam) / 4, total))

    x, y, z, total = lax.fori_loop(0, _DUPLICATION_STEPS, step, (x, y, z, zero))
    return (3 * total + _rj_tail(x, y, z, z)).reshape(shape)


def _rj(x: Array, y: Array, z: Array, p: Array) -> Array:
    return carlson(x, y, z, p)[1]


def elliprf(x: Float[ArrayLike, "*#batch"], y: Float[ArrayLike, "*#batch"], z: Float[ArrayLike, "*#batch"]) -> Array:
    """Carlson's ``R_F(x, y, z) = 1/2 int_0^inf dt / sqrt((t + x)(t + y)(t + z))``.

    ``x, y, z >= 0`` with at most one zero. ``F(phi | m) = sin(phi) R_F(cos^2 phi,
    1 - m sin^2 phi, 1)`` for ``|phi| <= pi/2``. As :func:`scipy.special.elliprf`.
    """
    args, dtype = _broadcast((x, y, z), ("x", "y", "z"))
    return _arrays.compiled_rows(rf, (0, 0, 0), *args).astype(dtype)


def elliprj(
    x: Float[ArrayLike, "*#batch"],
    y: Float[ArrayLike, "*#batch"],
    z: Float[ArrayLike, "*#batch"],
    p: Float[ArrayLike, "*#batch"],
) -> Array:
    """Carlson's ``R_J(x, y, z, p) = 3/2 int_0^inf dt / ((t + p) sqrt((t + x)(t + y)(t + z)))``.

    ``x, y, z >= 0`` with at most one zero, ``p > 0``. The incomplete integral of
    the third kind is ``Pi(n; phi | m) = F(phi | m) + n/3 sin^3(phi)
    R_J(cos^2 phi, 1 - m sin^2 phi, 1, 1 - n sin^2 phi)``. As
    :func:`scipy.special.elliprj` for ``p > 0``.
    """
    args, dtype = _broadcast((x, y, z, p), ("x", "y", "z", "p"))
    return _arrays.compiled_rows(_rj, (0, 0, 0, 0), *args).astype(dtype)


def reduced_amplitude(sn: Array, cn: Array) -> tuple[Array, Array, Array]:
    """``(h, sin r, cos r)`` with ``atan2(sn, cn) = h pi + r``, ``|r| <= pi/2`` (``h`` in -1, 0, 1)."""
    back = cn < 0
    h = jnp.where(back, jnp.where(sn < 0, -1.0, 1.0), 0.0).astype(sn.dtype)
    # not abs(cn): at cn = 0 its derivative is 0, which dropped the amplitude's derivative there
    return h, jnp.where(back, -sn, sn), jnp.where(back, -cn, cn)


def legendre(s: Array, c: Array, y: Array, n: Array) -> tuple[Array, Array]:
    """``F(r | m) = s R_F(x, y, 1)`` and ``Pi(n; r | m) = F + n/3 s^3 R_J(x, y, 1, 1 - n s^2)``
    for ``|r| <= pi/2``, ``s = sin r``, ``c = cos r >= 0``, ``x = c^2`` and ``y = 1 - m sin^2 r`` (one
    :func:`carlson` evaluation). For the partial integrals ``y`` is :func:`partial_y`; for the
    complete ones (``s = 1``) ``c`` is :func:`tiny_cos` and ``y`` is :func:`complete_y`
    (:func:`complete_arguments`). Taken in ``c``, not ``x``, so that the derivatives are finite at
    ``c = 0`` (:func:`_carlson_unit_z`)."""
    r_f, r_j = _carlson_unit_z(c, y, 1 - n * s * s)
    f = s * r_f
    return f, f + n / 3 * s * (s * s) * r_j


def legendre_joint(*args: tuple[Array, Array, Array, Array]) -> list[tuple[Array, Array]]:
    """:func:`legendre` of several sets of arguments ``(s, c, y, n)`` (each set broadcast to one
    shape of its own) from one Carlson loop, their elements laid side by side on one axis.

    Why: each loop is compiled on its own, and its derivatives too. The torque-free flow needs the
    integrals at its times and, per body, at time 0 and complete; two loops of 1000 x 101 and
    2 x 1000 elements compiled in 0.53-0.59 s and their gradient in 1.94-2.19 s, the same work as
    one loop in 0.43-0.45 s and 1.08-1.38 s (float64, one core of a 2-core AMD EPYC)."""
    groups = [jnp.broadcast_arrays(*a) for a in args]
    f, pi = legendre(*(jnp.concatenate([g[i].reshape(-1) for g in groups]) for i in range(4)))
    out, start = [], 0
    for g in groups:
        size, shape = g[0].size, g[0].shape
        out.append((f[start : start + size].reshape(shape), pi[start : start + size].reshape(shape)))
        start += size
    return out


def partial_y(c: Array, m: Array, mc: Array) -> Array:
    """``1 - m sin^2 r`` formed as ``mc + m cos^2 r`` (no cancellation near ``m = 1``)."""
    return jnp.maximum(mc + m * c * c, 0.0)


def complete_arguments(mc: Array) -> tuple[Array, Array, Array]:
    """:func:`legendre`'s ``(s, c, y)`` for the complete integrals ``K(m)`` and ``Pi(n | m)`` (the
    amplitude ``r = pi/2``): ``s = 1``, ``c`` :func:`tiny_cos` and ``y`` :func:`complete_y`, each
    shaped as ``mc = 1 - m``."""
    return jnp.ones_like(mc), jnp.broadcast_to(tiny_cos(mc), mc.shape), complete_y(mc, True)


def complete_y(mc: Array, whole: Array | bool) -> Array:
    """``y = mc`` of the complete integrals, raised to ``tiny``; the dummy 1 where ``whole`` is false
    (elements whose complete integrals are multiplied by 0), so that ``m = 1`` has finite
    derivatives. With ``x = tiny`` instead of 0 (sqrt's forward-mode derivative stays finite;
    ``R_F`` moves by ``O(sqrt(tiny))``, about 1e-154)."""
    return jnp.where(whole, jnp.maximum(mc, tiny(mc)), 1.0)
