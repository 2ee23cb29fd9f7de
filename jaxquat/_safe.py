"""The NaN-safe idiom, written once.

Functions such as ``sin(theta)/theta`` are smooth at ``theta = 0`` but their
direct formulas divide zero by zero there, and ``jnp.where`` alone does not save
the gradient (the untaken branch still propagates ``0 * nan = nan``). Every helper
here therefore

1. takes the *square* of the angle, ``s = theta**2``, which is a polynomial in the
   inputs and so has no singular derivative at zero (``|v|`` has one),
2. evaluates a Taylor polynomial in ``s`` on a small-argument operand and the
   direct formula on a *safe* operand that never enters the singular region,
3. selects between the two results with ``jnp.where``.

Both branches then have finite derivatives of every order, and the Taylor
polynomial carries enough terms that its truncation error is below float64
rounding at the switch point, so values, gradients and Hessians are right on
both sides of the switch.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax import Array

from . import _arrays, _fusion, _trig
from ._threads import split_across_devices

# Switch points (in s = theta**2). For sin(x)/x and cos(x) the first omitted
# term at s = 0.02 is s**5/11! ~ 8e-17; for atan(x)/x it is s**6/13 ~ 8e-20 at
# s = 1e-3. The direct branch loses about eps/s relative accuracy in its first
# derivative, i.e. ~1e-14 in float64 at these switch points.
_TRIG_SWITCH = 0.02
_ATAN_SWITCH = 1e-3

_SINC = (1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0)
_COS = (1.0, -1.0 / 2.0, 1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0)
# The derivatives' series take one term more than the values', to keep the same accuracy.
_SINC_DERIVATIVE = tuple(k * c for k, c in enumerate(_SINC + (-1.0 / 39916800.0,)))[1:]  # d/ds
_ATAN = (1.0, -1.0 / 3.0, 1.0 / 5.0, -1.0 / 7.0, 1.0 / 9.0, -1.0 / 11.0)
# d/d(x^2) of atan(x)/x = sum_k (-1)^k x^2k / (2k+1): sum_k>=1 k (-1)^k x^2(k-1) / (2k+1), taken up
# to x^2 = 0.1, where the direct formula's cancellation costs 1.5 / x^2 = 15 eps (at the value's
# switch, 1e-3, it cost 1500 eps: in float32 on an H100, whose atan2 differs from this CPU's,
# 1.5x the test's bound of 2000 eps, session 26). Terms to 0.1^K below the dtype's eps.
_ATAN_DERIVATIVE_SWITCH = 0.1
_ATAN_DERIVATIVE = {
    bits: tuple(k * (-1.0) ** k / (2 * k + 1) for k in range(1, terms + 1)) for bits, terms in ((32, 9), (64, 17))
}


def _horner(s: Array, coeffs: tuple[float, ...]) -> Array:
    acc = jnp.full_like(s, coeffs[-1])
    for c in coeffs[-2::-1]:
        acc = acc * s + c
    return acc


def _series_or_direct(s: Array, coeffs, direct, switch: float) -> Array:
    small = s < switch
    taylor = _horner(jnp.where(small, s, 0.0), coeffs)
    return jnp.where(small, taylor, direct(jnp.where(small, switch, s)))


@jax.custom_jvp
def sinc_cos_of_sq(s: Array) -> tuple[Array, Array]:
    """``(sin(x)/x, cos(x))`` as functions of ``s = x**2``, sharing one range reduction.

    Differentiated by its closed-form derivatives (a custom JVP), ``d cos/ds = -sinc/2`` and
    ``d sinc/ds = (cos - sinc) / (2 s)`` (the derivative of the series where the value takes
    the series), computed beside the values. Against JAX's derivative of the two branches and
    their selects, measured at 10^6 (this 2-core CPU, the gradient of ``sum(f(x) * W)``, minimum
    of 7 x 3 interleaved runs, float32 / float64): ``from_rotvec`` 1.6 / 3.6 against 2.6 /
    5.7 ms, ``slerp`` 29 / 56 against 27 / 67 ms."""
    return _sinc_cos_of_sq_parts(s)[:2]


def _sinc_cos_of_sq_parts(s: Array) -> tuple[Array, Array, Array]:
    """``(sinc, cos, d sinc/ds)`` of :func:`sinc_cos_of_sq`."""
    small = s < _TRIG_SWITCH
    s_small = jnp.where(small, s, 0.0)
    s_direct = jnp.where(small, _TRIG_SWITCH, s)
    # In kernel mode x and 1/x come from one rsqrt: two reciprocals fewer (until session 65 each a
    # bit-pattern guess and Newton's steps: slerp's gradient kernel 693 -> 639 operations; the
    # figures with _atan2_over_n_kernel's).
    if _trig.in_kernel():
        inv_x = _trig.rsqrt(s_direct)
        x = s_direct * inv_x
    else:
        x = jnp.sqrt(s_direct)
        inv_x = None
    sin, cos = _trig.sincos(x)
    sinc_direct = _trig.divide(sin, x) if inv_x is None else sin * inv_x
    sinc, cos = _arrays.scalars(
        jnp.where(small, _horner(s_small, _SINC), sinc_direct), jnp.where(small, _horner(s_small, _COS), cos)
    )
    residual = cos - sinc_direct
    d_direct = _trig.divide(residual, 2.0 * x * x) if inv_x is None else residual * (0.5 * inv_x * inv_x)
    d_sinc = jnp.where(small, _horner(s_small, _SINC_DERIVATIVE), d_direct)
    return sinc, cos, d_sinc


def _sinc_cos_jvp(parts):
    """The JVP rule of ``(sinc, cos)`` of ``s`` from ``parts(s) = (sinc, cos, d sinc/ds)``:
    ``d cos/ds = -sinc/2``."""

    def rule(primals, tangents):
        (s,), (ds,) = primals, tangents
        sinc, cos, d_sinc = parts(s)
        return (sinc, cos), (d_sinc * ds, -0.5 * sinc * ds)

    return rule


sinc_cos_of_sq.defjvp(_sinc_cos_jvp(_sinc_cos_of_sq_parts))


def _series_parts(s: Array) -> tuple[Array, Array, Array]:
    """:func:`_sinc_cos_of_sq_parts` for ``s`` below the switch: the series alone (the same values
    as the selection's there, to the bit)."""
    return _horner(s, _SINC), _horner(s, _COS), _horner(s, _SINC_DERIVATIVE)


def _small_batch_parts(s: Array) -> tuple[Array, Array, Array]:
    """``(sinc, cos, d sinc/ds)`` chosen by the whole batch: :func:`_series_parts` when every
    element of ``s`` is below the switch, else :func:`_sinc_cos_of_sq_parts` (a ``lax.cond``).
    ``s`` passes :func:`jaxquat._fusion.one_loop` first, so that on CPU the batch's test and the
    cond's operand read it from one loop; each was a kernel of its own that computed ``s`` again
    from what made it (in an RKMK4 step's derivatives, the last stage and the combination of the
    stages, about 115 operations). Measured on ``simulate``'s scan path (1000 bodies x 1000 RKMK4
    steps, one core of a 2-core Intel Xeon, least of 11, two processes each, alternated): torque-free
    float32 one ``jvp`` 13.4-13.7 -> 12.7-13.1 ms, the gradient 25.8-25.9 -> 24.6-25.4 ms; float64
    25.1-26.1 -> 24.2-24.8 ms and 56.0-57.5 -> 52.7-52.8 ms; with a PD torque (its stage attitudes
    chosen by the batch, value too) float32 forward 14.6 -> 14.3 ms, float64 gradient 162.4 ->
    158.3-158.5 ms. The same values.

    Where ``s`` is split between devices in one SPMD program (an explicitly sharded ``jit``:
    :func:`jaxquat._threads.split_across_devices`) each element selects its own branch, as
    :func:`_sinc_cos_of_sq_parts` does: there the batch's test is a cross-device ``all-reduce``,
    at every exponential of every step. 10^5 torque-free float32 bodies x 1000 RKMK4 steps on 2
    CPU devices of a 2-core AMD EPYC, ``jit`` of the sharded batch, min of 3 (session 70): float32
    gradient 5.90 -> 2.50-2.54 s, forward 541 -> 546-594 ms; float64 10.89 -> 5.07 s, 1237 ->
    1222 ms (a ``shard_map``, where each device tests its own shard: 2.06 s and 604 ms, 4.57 s and
    1094 ms, the same hour). Under ``AxisType.Auto`` axes the type does not say, and the test
    stays batch-wide."""
    if not split_across_devices(s):
        (s,) = _fusion.one_loop([s])
    return parts_by_batch(s)


def parts_by_batch(s: Array) -> tuple[Array, Array, Array]:
    """``(sinc, cos, d sinc/ds)`` of :func:`_small_batch_parts` for an ``s`` its caller has already
    computed in a loop of its own (:func:`jaxquat._fusion.one_loop`): the series alone when every
    element is below the switch, else the element-wise selection (a ``lax.cond``); split between
    devices, the selection."""
    if split_across_devices(s):
        return _sinc_cos_of_sq_parts(s)
    return jax.lax.cond(jnp.all(s < _TRIG_SWITCH), _series_parts, _sinc_cos_of_sq_parts, s)


@jax.custom_jvp
def sinc_cos_of_sq_small_batch(s: Array) -> tuple[Array, Array]:
    """:func:`sinc_cos_of_sq` for arguments nearly always below its series switch (an integrator
    step's ``|theta|^2 / 4``), its value and derivatives chosen by one ``lax.cond`` on the whole
    batch (:func:`_small_batch_parts`): the series alone when every element of ``s`` is below
    the switch, else the per-element selection. The same values and derivatives, to the bit.
    For the stage attitudes ``q Exp(theta_i)`` of an RKMK step on CPU
    (:mod:`jaxquat.integration.struct_of_arrays`), where the cond cuts the stage's loop in two but
    saves the direct branch's square root, range reduction, two polynomials and two divisions at
    three of a step's four exponentials. 1000 bodies x 1000 RKMK4 steps under the PD law (one
    core of this 2-core EPYC, least of 7, the step's last exponential differentiated through the
    cond as well): float32 forward 13.4 ->
    12.2 ms, gradient 74.1 -> 62.7 ms, one ``jvp`` 27.8 -> 24.7 ms; float64 28.7 -> 23.4, 175 ->
    143 and 53.8 -> 46.6 ms. For the step's last exponential the cond on the value cost more
    than it saved (torque-free, float32 forward 5.8 -> 6.3 ms)."""
    return _small_batch_parts(s)[:2]


sinc_cos_of_sq_small_batch.defjvp(_sinc_cos_jvp(_small_batch_parts))


@jax.custom_jvp
def atan2_over_n(nsq: Array, w: Array) -> Array:
    """``atan2(n, w) / n`` with ``n = sqrt(nsq) >= 0``, smooth as ``n -> 0`` for ``w > 0``.

    For ``w > 0`` and small ``n/w`` it is ``(1/w) * atan(x)/x`` with ``x = n/w``,
    an even series in ``x``. For ``w <= 0`` the function really is singular at
    ``n = 0`` (the quaternion is real and negative); there the result is finite
    but meaningless and callers must handle that case themselves.

    Differentiated by its closed-form partials (a custom JVP), ``df/dw = -1/(n^2 + w^2)`` and
    ``df/dnsq = (w/(n^2 + w^2) - f) / (2 nsq)`` (the derivative of the series where the value
    takes the series), computed beside the value. JAX's derivative of the two branches and their
    selects left XLA on CPU more separate passes over the batch: measured at 10^6 (this 2-core
    CPU, the gradient of ``sum(f(x) * W)``, minimum of 7 x 3 interleaved runs, float32 /
    float64), ``to_rotvec`` 16 / 33 against 37 / 71 ms, ``slerp`` 29 / 56 against 45 / 95 ms.
    ``df/dnsq`` takes its series up to ``x^2 = nsq / w^2 = 0.1`` (the value up to ``1e-3``):
    the direct branch loses about ``1.5 eps / x^2`` relative accuracy to cancellation, 15 eps
    there. Its term is ``x^2`` times smaller than the rest of a rotation vector's Jacobian.
    """
    return _atan2_over_n_parts(nsq, w)[0]


def _atan2_over_n_parts(nsq: Array, w: Array) -> tuple[Array, Array, Array]:
    """``(f, df/dnsq, df/dw)`` of :func:`atan2_over_n`."""
    if _trig.in_kernel():
        return _atan2_over_n_kernel(nsq, w)
    small, small_n = _atan_series_rows(nsq, w)
    w_safe = jnp.where(small, w, 1.0)
    x2 = jnp.where(small, _trig.divide(nsq, w_safe * w_safe), 0.0)
    taylor = _trig.divide(_horner(x2, _ATAN), w_safe)
    # d/dnsq of (1/w) sum_k a_k (nsq/w^2)^k, on its own, wider interval
    w_n = jnp.where(small_n, w, 1.0)
    taylor_n = _atan_derivative_series(nsq, small_n, _trig.divide(1.0, w_n))
    degenerate = small | (nsq <= 0)
    nsq_safe = jnp.where(degenerate, 1.0, nsq)
    n_safe = _trig.sqrt(nsq_safe)
    f = jnp.where(small, taylor, _trig.divide(_trig.atan2(n_safe, w), n_safe))
    rsq = nsq + w * w
    r = _trig.divide(1.0, jnp.where(rsq > 0, rsq, 1.0))
    nsq_n = jnp.where(small_n | (nsq <= 0), 1.0, nsq)
    f_n = jnp.where(small_n, taylor_n, _trig.divide(w * r - f, 2.0 * nsq_n))
    f, f_n, f_w = _arrays.scalars(f, f_n, -r)
    return f, f_n, f_w


def _atan_series_rows(nsq: Array, w: Array) -> tuple[Array, Array]:
    """The rows where :func:`atan2_over_n`'s value takes its series, and (a wider set) where its
    derivative in ``nsq`` does."""
    return (w > 0) & (nsq < _ATAN_SWITCH * w * w), (w > 0) & (nsq < _ATAN_DERIVATIVE_SWITCH * w * w)


def _atan_derivative_series(nsq: Array, rows: Array, inv: Array) -> Array:
    """``d/dnsq`` of ``(1/w) atan(x)/x`` (``x^2 = nsq / w^2``) by its series, on ``rows``;
    ``inv`` is ``1/w`` there."""
    x2 = jnp.where(rows, nsq * (inv * inv), 0.0)
    return _horner(x2, _ATAN_DERIVATIVE[64 if nsq.dtype == jnp.float64 else 32]) * (inv * inv * inv)


def _atan2_over_n_kernel(nsq: Array, w: Array) -> tuple[Array, Array, Array]:
    """:func:`_atan2_over_n_parts` in kernel mode, the same branches and series on three
    reciprocals instead of eight (:func:`jaxquat._trig.reciprocal`; until session 65 each was a
    bit-pattern guess and Newton's steps): ``rsqrt(nsq)`` gives ``n`` and ``1/n``; one reciprocal of
    ``max(n, |w|)`` gives the ratio inside ``atan2`` and, on the series' rows (where ``|w| > n``),
    ``1/w``; the third is ``1 / (n^2 + w^2)``; ``atan``'s own argument reduction keeps its own.
    ``df/dnsq = (w r - f) / (2 nsq)`` is ``(w r - f) (1/n)^2 / 2``. Its operations in kernel
    mode 399 -> 239 (the kernel of ``to_rotvec``'s gradient 523 -> 391 HLO operations). At 10^6
    (one pinned core of a 2-core Intel Xeon with AVX-512, least of 15, base and this side by side
    on the two cores, then swapped; with :func:`sinc_cos_of_sq`'s kernel form, which ``slerp``
    shares): the gradient of ``sum(to_rotvec(q))`` 9.3-9.7 -> 8.1-8.4 ms in float32 and 19-25 ->
    17-18 ms in float64; ``slerp``'s value 13.8 -> 11.4-11.6 ms and gradient 17.1-17.4 -> 13.8-14.0
    ms in float32, 29-38 -> 26 ms and 34-44 -> 32 ms in float64."""
    small, small_n = _atan_series_rows(nsq, w)  # small_n contains small
    degenerate = small | (nsq <= 0)
    aw = jnp.abs(w)
    nsq_safe = jnp.where(degenerate, 1.0, nsq)  # as in _atan2_over_n_parts: n = 1 where nsq <= 0
    rs = _trig.rsqrt(nsq_safe)
    n = jnp.where(small, 0.0, nsq_safe * rs)
    swap = n > aw  # never on the series' rows
    larger = jnp.where(swap, n, aw)
    inv = _trig.reciprocal(jnp.where(larger == 0, 1.0, larger))  # 1/w on small_n's rows
    angle = _trig.atan2_of_ratio(jnp.where(swap, aw, n) * inv, swap, w)  # atan2(n, w)
    x2 = jnp.where(small, nsq * (inv * inv), 0.0)
    f = jnp.where(small, _horner(x2, _ATAN) * inv, angle * rs)
    taylor_n = _atan_derivative_series(nsq, small_n, inv)
    rsq = nsq + w * w
    r = _trig.reciprocal(jnp.where(rsq > 0, rsq, 1.0))
    direct_n = (w * r - f) * (0.5 * rs * rs)
    return f, jnp.where(small_n, taylor_n, direct_n), -r


@atan2_over_n.defjvp
def _atan2_over_n_jvp(primals, tangents):
    (nsq, w), (dnsq, dw) = primals, tangents
    f, f_n, f_w = _atan2_over_n_parts(nsq, w)
    return f, f_n * dnsq + f_w * dw


def norm_sq(x: Array, axis: int = -1) -> Array:
    """Sum of squares along ``axis``."""
    return _arrays.dot(x, x) if axis in (-1, x.ndim - 1) else jnp.sum(x * x, axis=axis)


def safe_sqrt(s: Array) -> Array:
    """``sqrt(s)`` whose derivative at ``s = 0`` is 0 (a subgradient of ``|v|``) instead of inf.

    Only an exact zero is special-cased: a NaN ``s`` gives NaN (a NaN input must never
    come out as a plausible 0)."""
    zero = s == 0
    return jnp.where(zero, 0.0, _trig.sqrt(jnp.where(zero, 1.0, s)))


def safe_norm(x: Array, axis: int = -1) -> Array:
    """Euclidean norm with gradient 0 (a valid subgradient) at the zero vector."""
    return safe_sqrt(norm_sq(x, axis))


def safe_atan2(y: Array, x: Array) -> Array:
    """``atan2(y, x)``, returning 0 with zero gradient at ``(0, 0)`` instead of NaN."""
    zero = (x == 0) & (y == 0)
    return jnp.where(zero, 0.0, _trig.atan2(y, jnp.where(zero, 1.0, x)))


def safe_hypot(x: Array, y: Array) -> Array:
    """``hypot(x, y)`` with gradient 0 at ``(0, 0)``."""
    return safe_sqrt(x * x + y * y)


def rescaled(q: Array) -> Array:
    """``q`` times the power of two ``2^-E`` where ``2^E <= max_i |q_i| < 2^(E+1)``.

    The scaling is exact (only the exponent changes), so a scale-invariant function of
    the result equals the function of ``q`` and has the same derivative (its gradient is
    orthogonal to ``q``); but no component squared can underflow or overflow, which in
    float32 turned ``angle(1e-25 (1, 1, 0, 0))`` into 0 instead of pi/2. A zero ``q``
    stays zero, a NaN stays NaN.

    The factor is built from the exponent bits (``2^-E`` has biased exponent
    ``2 bias - (E + bias)``) because ``frexp``/``ldexp`` doubled the time of
    ``to_rotvec`` at 10^6 (3.6 -> 7.5 ms in float32 on the reference 2-core machine); this
    costs 3.6 -> 4.6 ms (``angle``: 1.8 -> 3.3 ms), the price of exact answers at any scale.
    """
    return q * _rescaling([q[..., i] for i in range(q.shape[-1])])[..., None]


def rescaled_components(*c: Array) -> list[Array]:
    """:func:`rescaled` on the components of a quaternion (or vector) given apart.

    For kernels written on components (:func:`jaxquat._arrays.components`): the gradient of
    ``to_rotvec`` at 10^6 (this 2-core CPU, ``sum(f(q) * W)``, minimum of 7 x 3 interleaved
    runs) took 16 / 33 ms (float32 / float64) against 20 / 41 ms with the ``(..., 4)`` array
    scaled before the split."""
    scale = _rescaling(list(c))
    return [x * scale for x in c]


def _rescaling(c: list[Array]) -> Array:
    """The power of two ``2^-E`` with ``2^E <= max_i |c_i| < 2^(E+1)`` (no gradient)."""
    big = jnp.abs(c[0])
    for x in c[1:]:
        big = jnp.maximum(big, jnp.abs(x))
    info = jnp.finfo(big.dtype)
    nmant, bias = int(info.nmant), int(info.maxexp) - 1
    itype = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[info.bits // 8]
    mask = ((1 << (info.bits - 1 - nmant)) - 1) << nmant
    bits = jax.lax.bitcast_convert_type(jax.lax.stop_gradient(big), itype)
    return jax.lax.bitcast_convert_type(((2 * bias) << nmant) - (bits & mask), big.dtype)


# Coefficient functions of the SO(3) Jacobians, as series in s = theta**2 (exact
# rational coefficients: (-1)^k/(2k+2)!, (-1)^k/(2k+3)!, and -(-1)^n B_2n/(2n)!).
# Switch at s = 0.5: the first omitted terms are below 1e-21, and the direct
# formulas lose at most ~eps/s = 5e-16 to cancellation there.
_JAC_SWITCH = 0.5
_ONE_MINUS_COS = (
    0.5,
    -1 / 24,
    1 / 720,
    -1 / 40320,
    1 / 3628800,
    -1 / 479001600,
    1 / 87178291200,
    -1 / 20922789888000,
    1 / 6402373705728000,
)
_X_MINUS_SIN = (
    1 / 6,
    -1 / 120,
    1 / 5040,
    -1 / 362880,
    1 / 39916800,
    -1 / 6227020800,
    1 / 1307674368000,
    -1 / 355687428096000,
    1 / 121645100408832000,
)
_JINV = (
    1 / 12,
    1 / 720,
    1 / 30240,
    1 / 1209600,
    2.08767569878681e-08,
    5.284190138687493e-10,
    1.3382536530684679e-11,
    3.3896802963225827e-13,
    8.586062056277845e-15,
    2.174868698558062e-16,
)


def one_minus_cos_over_sq(s: Array) -> Array:
    """``(1 - cos x) / x**2`` as a function of ``s = x**2``."""
    return _series_or_direct(s, _ONE_MINUS_COS, lambda u: (1 - _trig.cos(jnp.sqrt(u))) / u, _JAC_SWITCH)


def x_minus_sin_over_cube(s: Array) -> Array:
    """``(x - sin x) / x**3`` as a function of ``s = x**2``."""

    def direct(u):
        x = jnp.sqrt(u)
        return (x - _trig.sin(x)) / (u * x)

    return _series_or_direct(s, _X_MINUS_SIN, direct, _JAC_SWITCH)


def jacobian_inverse_coeff_truncated(order: int, s: Array | None = None) -> Any:
    """The terms of :func:`jacobian_inverse_coeff`'s series (``_JINV``) that an RKMK method of
    ``order`` p keeps in ``dexp^-1`` (Munthe-Kaas 1999): ``1/12`` (p <= 4), ``+ s/720``
    (p = 5, 6), ``+ s^2/30240`` (p >= 7); ``s = |theta|^2``, needed only for p >= 5. Shared by
    the row-form and the struct-of-arrays Lie steps, so their truncations cannot drift apart."""
    coef: Any = 1.0 / 12.0
    if order >= 5:
        if s is None:
            raise ValueError(f"an RKMK method of order {order} needs |theta|^2")
        coef = coef + s / 720.0 + (s * s / 30240.0 if order >= 7 else 0.0)
    return coef


def jacobian_inverse_coeff(s: Array) -> Array:
    """``1/x**2 - cot(x/2) / (2 x)`` as a function of ``s = x**2`` (finite for 0 <= x < 2 pi)."""

    def direct(u):
        x = jnp.sqrt(u)
        return 1 / u - _trig.cos(x / 2) / (2 * x * _trig.sin(x / 2))

    return _series_or_direct(s, _JINV, direct, _JAC_SWITCH)
