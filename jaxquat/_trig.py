"""``sin``, ``cos`` and ``atan2`` from polynomials and selects, which XLA vectorises.

XLA on CPU lowers ``jnp.sin``, ``jnp.cos`` and ``jnp.arctan2`` to scalar libm calls:
about 7, 7 and 16 ns per element on the reference 2-core machine, against 0.3 ns for
a multiply-add, so they dominated every rotation op that takes an angle (slerp, the
rotation-vector and Euler conversions, the exponential map in the Lie-group
solvers). The versions here use only arithmetic, ``round`` and ``where``, which XLA
fuses and vectorises, and are within a few units in the last place of libm in float32
and float64 (``tests/test_trig.py`` measures the error on millions of arguments).

Method (textbook facts, the coefficients are the classical minimax ones of Cody and
Waite / Moshier, re-derived constants checked against numpy in the tests):

- ``sincos``: Cody-Waite reduction ``r = x - k pi/2`` with ``pi/2`` split in three
  parts, the first two of whose products with ``k`` are exact for ``|k| < 2**21`` in
  float64 (``|x| < 3.2e6``) and ``|k| < 2**16`` in float32 (``|x| < 1.0e5``), with or
  without fused multiply-adds (past that the result loses accuracy gradually, as any
  reduction without Payne-Hanek does), then odd and even polynomials on ``|r| <= pi/4``
  and a quadrant swap.
- ``atan2``: ``a = min(|x|, |y|) / max(|x|, |y|)`` in ``[0, 1]``, reduced once more by
  ``atan(a) = pi/4 + atan((a - 1)/(a + 1))`` above ``tan(pi/8)`` (float32) or 0.66
  (float64), a polynomial (float32) or rational (float64) kernel, then the octant
  and quadrant by reflections. Signed zeros follow numpy: ``atan2(+-0, -0) = +-pi``.

Only on CPU: when JAX's default backend is CPU these polynomials are traced, otherwise
``jnp.sin``, ``jnp.cos``, ``jnp.arctan2`` (GPU and TPU evaluate their own transcendental
functions vectorised, and their fusion heuristics are XLA's to choose). Decided at trace
time from ``jax.default_backend()``, not by ``jax.lax.platform_dependent``: the latter's
folded conditional cost the CPU path time (float32 at 10^6, this 2-core CPU: ``slerp``
15.3-17.2 ms -> 18.4-22.4 ms, ``from_euler`` 3.2-4.3 -> 4.7-4.9 ms and twice the compile
time). Either choice gives correct values anywhere: it only decides which fast path runs
(a computation placed on a CPU device from a GPU process gets the ``jnp`` functions).
``tests/test_trig.py`` checks both paths.

Derivatives are defined by ``custom_jvp`` from the exact identities
``sin' = cos``, ``cos' = -sin`` and ``d atan2(y, x) = (x dy - y dx) / (x^2 + y^2)``,
so gradients are as accurate as the values.

Kernel mode (:func:`kernel_mode`, :func:`in_kernel`): while :mod:`jaxquat._derivatives` traces
an op's derivative kernel, :func:`divide` and :func:`sqrt` (and ``atan2``, which divides) use
:func:`reciprocal` and :func:`rsqrt`, built from multiplies: XLA's CPU fusion counts a floating
divide or square root as expensive and never duplicates one, so each one with two users became
an array of its own, written and read back, and the kernel several loops instead of one
(measured there). Outside kernel mode they are ``/`` and ``jnp.sqrt``.
"""

from __future__ import annotations

import contextlib
import contextvars

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _fusion

# sin(r) = r + r^3 P(r^2), cos(r) = 1 - r^2/2 + r^4 Q(r^2) on |r| <= pi/4 (Moshier's
# double-precision kernels; good to float32 rounding too).
_SIN = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
_COS = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)
_SIN32 = (-1.6666654611e-1, 8.3321608736e-3, -1.9515295891e-4)
_COS32 = (4.166664568298827e-2, -1.388731625493765e-3, 2.443315711809948e-5)
# pi/2 = P1 + P2 + P3: P1 and P2 with few enough significant bits that k * P1 and k * P2 are
# exact (float64: 31 and 32 bits, |k| < 2^21; float32: 8 and 7 bits, |k| < 2^16), P3 the rest
# to the dtype's precision. Until session 58 the float32 P2 had 11 bits, so k * P2 rounded
# for |k| > 2^13 (|x| > 1.3e4) unless the multiply and subtract were contracted into a fused
# multiply-add: sin and cos at |x| <= 1e5 were 8.0 ulp off on a CPU without FMA (XLA limited
# to AVX), against 0.75 with it; now 0.7-0.8 ulp both ways.
_PIO2_64 = (1.57079632673412561417e00, 6.07710050630396597660e-11, 2.02226624871116645580e-21)
_PIO2_32 = (1.5703125, 4.84466552734375e-4, -6.397578431460715e-7)

# atan(t) = t + t^3 P(t^2) / Q(t^2) on |t| <= 0.66 (float64); t + t^3 R(t^2) on |t| <= 1 (float32).
_ATAN_P = (
    -6.485021904942025371773e1,
    -1.228866684490136173410e2,
    -7.500855792314704667340e1,
    -1.615753718733365076637e1,
    -8.750608600031904122785e-1,
)
_ATAN_Q = (
    1.945506571482613964425e2,
    4.853903996359136964868e2,
    4.328810604912902668951e2,
    1.650270098316988542046e2,
    2.485846490142306297962e1,
    1.0,
)
# R of degree 8 on the whole of [0, 1], no argument reduction: fitted (session 61) to the relative
# error of atan by least squares reweighted towards the largest errors (Lawson), 2.6e-9 in exact
# arithmetic, 1.11 ulp evaluated in float32 by Horner's rule at 4e6 points. It replaced Cephes'
# atanf polynomial of degree 3 on [0, tan(pi/8)] after the reduction t -> (t - 1) / (t + 1) above
# it, whose division is a reciprocal by Newton's steps in a kernel: 26 operations fewer per atan2.
_ATAN32 = (
    -0.33333299079668843,
    0.1999854804896232,
    -0.14264239610591065,
    0.10952176891346682,
    -0.0840342932723412,
    0.05795730888993047,
    -0.03117762863596214,
    0.010914521170806072,
    -0.0017936092789473464,
)


def _poly(z: Array, coeffs) -> Array:
    """``c0 + c1 z + c2 z^2 + ...`` by Horner's rule."""
    acc = jnp.asarray(coeffs[-1], z.dtype)
    for c in coeffs[-2::-1]:
        acc = acc * z + c
    return acc


def _is64(x: Array) -> bool:
    return jnp.dtype(x.dtype) == jnp.float64


_KERNEL = contextvars.ContextVar("jaxquat_kernel_mode", default=False)


@contextlib.contextmanager
def kernel_mode():
    """Trace in kernel mode (see the module's docstring) inside the ``with`` block."""
    token = _KERNEL.set(True)
    try:
        yield
    finally:
        _KERNEL.reset(token)


def in_kernel() -> bool:
    """Whether a derivative kernel is being traced (:func:`kernel_mode`)."""
    return _KERNEL.get()


# Bit-pattern first guesses: 1/a from (MAGIC - bits(a)), 1/sqrt(a) from (MAGIC - bits(a) / 2), each
# within 12.5 % and 0.2 %; Newton's iterations square the relative error (1/a) or about that (1/sqrt(a)).
_RECIPROCAL = {32: (0x7EF311C3, 4), 64: (0x7FDE623822FC16E6, 5)}
_RSQRT = {32: (0x5F375A86, 3), 64: (0x5FE6EB50C7B537A9, 4)}


def _guess(a: Array, magic: int, shift: int) -> Array:
    itype = jnp.int64 if _is64(a) else jnp.int32
    bits = jax.lax.bitcast_convert_type(a, itype)
    return jax.lax.bitcast_convert_type(jnp.asarray(magic, itype) - (bits >> shift), a.dtype)


@jax.custom_jvp
def reciprocal(y: Array) -> Array:
    """``1 / y`` from multiplies only: a bit-pattern guess, then Newton's ``r + r (1 - |y| r)``
    (the residual first, so a power of two comes out exact, where ``r (2 - |y| r)`` stalls an ulp
    short). Within 0.5 ulp of ``1 / y`` for ``2^-126 <= |y| < 2^125`` (float32; ``2^-1022`` and
    ``2^1021`` in float64; ``tests/test_trig.py``) where XLA fuses the residual's multiply and
    subtract into one fused multiply-add (FMA: CPUs that have it, x86-64 since 2013 and every ARM64
    one, and GPUs), within 1.25 ulp where it rounds the product first (measured 1.24 ulp in both
    dtypes, XLA limited to AVX: ``--xla_cpu_max_isa=AVX``); beyond that range (where the guess's
    exponent leaves the normal range) and at zero, a finite but wrong number; NaN gives NaN.
    float16 and bfloat16 go through float32.

    Without FMA the bound holds for ``|y| < 2^100`` (float32; ``2^970`` in float64, the suite checks
    below ``2^64`` and ``2^512``): above, ``1 / y`` is near the bottom of the normal range and a
    correction ``r (1 - |y| r)`` subnormal, which XLA's CPU code flushes to zero (measured: up to 5 %
    off at ``2^124``, 4 % at ``2^1020``). Scaling ``|y|`` down there by a power of two and the result
    back (a compare, a select and two multiplies) removed that, but cost 7 % of ``to_rotvec``'s
    gradient at 10^6 rotations (float32, 10.05-10.95 -> 10.96-11.54 ms, one core) for arguments
    no rotation reaches, so it is not done."""
    if jnp.finfo(y.dtype).bits < 32:  # float16, bfloat16: in float32
        return reciprocal(y.astype(jnp.float32)).astype(y.dtype)
    a = jnp.abs(y)
    magic, steps = _RECIPROCAL[64 if _is64(y) else 32]
    r = _guess(a, magic, 0)
    for _ in range(steps):
        r = r + r * (1.0 - a * r)
    return jnp.where(jnp.signbit(y), -r, r)


@reciprocal.defjvp
def _reciprocal_jvp(primals, tangents):
    (y,), (dy,) = primals, tangents
    r = reciprocal(y)
    return r, -r * r * dy


@jax.custom_jvp
def rsqrt(x: Array) -> Array:
    """``1 / sqrt(x)`` from multiplies only: a bit-pattern guess, then Newton's
    ``r + r (1 - x r^2) / 2``. Within 1 ulp for normal ``x > 0`` (``tests/test_trig.py``; 1.25
    ulp without fused multiply-adds, measured 1.21: see :func:`reciprocal`); at
    zero a large finite number (so ``x * rsqrt(x)`` is 0); NaN gives NaN. float16 and bfloat16
    go through float32."""
    if jnp.finfo(x.dtype).bits < 32:  # float16, bfloat16: in float32
        return rsqrt(x.astype(jnp.float32)).astype(x.dtype)
    magic, steps = _RSQRT[64 if _is64(x) else 32]
    r = _guess(x, magic, 1)
    for _ in range(steps):
        r = r + 0.5 * r * (1.0 - x * r * r)
    return r


@rsqrt.defjvp
def _rsqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    r = rsqrt(x)
    return r, -0.5 * r * r * r * dx


def divide(a, b):
    """``a / b``; in kernel mode ``a * reciprocal(b)`` (callers keep ``b`` finite and non-zero)."""
    return a * reciprocal(b) if in_kernel() else a / b


def sqrt(x: Array) -> Array:
    """``sqrt(x)``; in kernel mode ``x * rsqrt(x)`` (callers keep ``x`` finite and ``>= 0``; 0 gives 0)."""
    return x * rsqrt(x) if in_kernel() else jnp.sqrt(x)


def _sincos_value(x: Array):
    wide = _is64(x)
    p1, p2, p3 = _PIO2_64 if wide else _PIO2_32
    k = jnp.round(x * (2 / np.pi))
    r = ((x - k * p1) - k * p2) - k * p3
    z = r * r
    s = r + r * z * _poly(z, _SIN if wide else _SIN32)
    c = 1.0 - 0.5 * z + z * z * _poly(z, _COS if wide else _COS32)
    quadrant = k.astype(jnp.int32) & 3
    swap = (quadrant & 1) == 1
    sin = jnp.where(swap, c, s)
    cos = jnp.where(swap, s, c)
    sin = jnp.where(quadrant >= 2, -sin, sin)
    cos = jnp.where((quadrant == 1) | (quadrant == 2), -cos, cos)
    return sin, cos


def _cpu() -> bool:
    return jax.default_backend() == "cpu"


def on_cpu(cpu, other, *args):
    """``cpu(*args)`` when JAX's default backend is CPU, else ``other(*args)`` (at trace time)."""
    return cpu(*args) if _cpu() else other(*args)


def is_cpu() -> bool:
    """Whether JAX's default backend is CPU (at trace time; what :func:`on_cpu` asks)."""
    return _cpu()


@jax.custom_jvp
def sincos(x: Array):
    """``(sin x, cos x)``, vectorisable, one shared range reduction (on CPU; ``jnp`` elsewhere)."""
    return on_cpu(_sincos_value, lambda x: (jnp.sin(x), jnp.cos(x)), x)


@sincos.defjvp
def _sincos_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = sincos(x)
    return (s, c), (c * dx, -s * dx)


def sin(x: Array) -> Array:
    return sincos(x)[0]


def cos(x: Array) -> Array:
    return sincos(x)[1]


def _atan_unit(a: Array) -> Array:
    """``atan(a)`` for ``0 <= a <= 1``."""
    if not _is64(a):  # float32: one polynomial on [0, 1]
        z = a * a
        return a + a * z * _poly(z, _ATAN32)
    big = a > 0.66
    t = jnp.where(big, divide(a - 1.0, a + 1.0), a)
    z = t * t
    kernel = t + t * z * divide(_poly(z, _ATAN_P), _poly(z, _ATAN_Q))
    # pi/4 as a double plus the part of it a double cannot hold
    return jnp.where(big, (0.7853981633974483 + kernel) + 3.061616997868383e-17, kernel)


@jax.custom_jvp
def atan2(y: Array, x: Array) -> Array:
    """``atan2(y, x)`` in ``[-pi, pi]``, vectorisable (on CPU; ``jnp.arctan2`` elsewhere);
    ``atan2(0, 0) = 0``."""
    return on_cpu(_atan2_value, jnp.arctan2, y, x)


def _atan2_value(y: Array, x: Array) -> Array:
    # The ratio through _fusion.fusible: the polynomial reads it several times, and XLA left the
    # division a kernel of its own. to_rotvec's value at 10^6 rotations (one core, least of 7,
    # two processes each): 5.17-5.19 -> 4.54-4.73 ms in float32, 26.8-27.2 -> 21.3-22.7 ms in float64.
    ax, ay = jnp.abs(x), jnp.abs(y)
    swap = ay > ax
    num = jnp.where(swap, ax, ay)
    den = jnp.where(swap, ay, ax)
    r = atan2_of_ratio(_fusion.fusible(divide(num, jnp.where(den == 0, 1.0, den))), swap, x)
    return jnp.where(jnp.signbit(y), -r, r)


def atan2_of_ratio(ratio: Array, swap: Array, x: Array) -> Array:
    """``atan2(|y|, x)`` from ``ratio = min(|y|, |x|) / max(|y|, |x|)`` and ``swap = |y| > |x|``:
    :func:`atan2`'s value for a caller that has the reciprocal of the larger for other uses too
    (``jaxquat._safe``'s kernel form of ``atan2_over_n``; not differentiated on its own)."""
    r = _atan_unit(ratio)
    r = jnp.where(swap, (np.pi / 2) - r, r)
    return jnp.where(jnp.signbit(x), np.pi - r, r)


@atan2.defjvp
def _atan2_jvp(primals, tangents):
    (y, x), (dy, dx) = primals, tangents
    return atan2(y, x), divide(x * dy - y * dx, x * x + y * y)
