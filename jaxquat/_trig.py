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
an op's derivative kernel, :func:`divide` and :func:`sqrt` (and ``atan2``, which divides), like
:func:`reciprocal` and :func:`rsqrt`, pass their result through :func:`jaxquat._fusion.fusible`
and differentiate through it: XLA's CPU fusion emitters count a floating division or square root
as expensive and never duplicate one, so each one with two users became an array of its own,
written and read back, and the kernel several loops instead of one. Until session 65 these
four were built from multiplies (a bit-pattern guess and Newton's iterations, within 0.5-1.25
ulp on a range of arguments); now they are IEEE divisions and square roots (correctly rounded;
``rsqrt`` is two of them), and faster (in :func:`reciprocal`'s docstring). Outside kernel mode
:func:`divide` and :func:`sqrt` are ``/`` and ``jnp.sqrt``.
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


@jax.custom_jvp
def reciprocal(y: Array) -> Array:
    """``1 / y``, correctly rounded, through :func:`jaxquat._fusion.fusible`: one loop with its
    consumers in a derivative kernel (callers keep ``y`` finite and non-zero; ``1 / 0`` is
    infinite). Its derivative ``-r^2 dy`` reads the fused ``r``, so that the division keeps one
    user under differentiation too.

    Until session 65 it was built from multiplies (a bit-pattern guess, then Newton's ``r + r (1 -
    |y| r)``: within 0.5 ulp with fused multiply-adds on ``2^-126 <= |y| < 2^125``, 1.25 ulp
    without, a wrong finite number beyond), because XLA would not fuse a division with several
    users. Measured at 10^6 rotations (one core of a 2-core AMD EPYC, least of 7, three processes
    each in float32 and two in float64, every kernel-mode division, square root, reciprocal and
    ``rsqrt`` changed together; float32 / float64): ``to_euler`` 5.56-5.63 -> 3.84-3.89 /
    31.2 -> 20.8-22.4 ms and its gradient 5.94-6.15 -> 4.16-4.26 / 32.5-33.7 -> 23.3 ms,
    ``slerp`` 10.1-10.4 -> 8.5-8.9 / 43.9-46.8 -> 34.6-34.8 ms and its gradient 12.4-12.6 ->
    10.6-10.7 / 49.2-51.0 -> 38.9-40.7 ms, ``to_rotvec``'s gradient 6.74-6.87 -> 5.31-5.39 /
    34.3-36.4 -> 27.8-28.5 ms; the kernels' count unchanged. (``rsqrt`` as XLA's own was up to 5 %
    faster in float32, and less accurate: see :func:`rsqrt`.)"""
    return _fusion.fusible(1.0 / y)


@reciprocal.defjvp
def _reciprocal_jvp(primals, tangents):
    (y,), (dy,) = primals, tangents
    r = reciprocal(y)
    return r, -r * r * dy


@jax.custom_jvp
def rsqrt(x: Array) -> Array:
    """``1 / sqrt(x)`` for ``x > 0`` (infinite at zero) as two correctly rounded operations,
    within 2 ulp on any CPU (measured 1.46 in float64 and 1.48 in float32), through
    :func:`jaxquat._fusion.fusible`; its derivative ``-r^3 dx / 2`` reads the fused ``r``. The
    root passes through ``fusible`` as well, or XLA rewrites ``1 / sqrt`` into its own ``rsqrt``
    (1.68 ulp in float32 on this CPU, and an approximation whose accuracy is the CPU's). Until
    session 65 a bit-pattern guess and Newton's iterations (:func:`reciprocal` has why and the
    figures)."""
    return _fusion.fusible(1.0 / _fusion.fusible(jnp.sqrt(x)))


@rsqrt.defjvp
def _rsqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    r = rsqrt(x)
    return r, -0.5 * r * r * r * dx


@jax.custom_jvp
def _kernel_divide(a: Array, b: Array) -> Array:
    return _fusion.fusible(a / b)


@_kernel_divide.defjvp
def _kernel_divide_jvp(primals, tangents):
    (a, b), (da, db) = primals, tangents
    q = _kernel_divide(a, b)
    return q, _kernel_divide(da - q * db, b)


@jax.custom_jvp
def _kernel_sqrt(x: Array) -> Array:
    return _fusion.fusible(jnp.sqrt(x))


@_kernel_sqrt.defjvp
def _kernel_sqrt_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    y = _kernel_sqrt(x)
    return y, _kernel_divide(0.5 * dx, y)


def divide(a, b):
    """``a / b``; in kernel mode through :func:`jaxquat._fusion.fusible`, its derivative reading
    the fused quotient (callers keep ``b`` finite and non-zero)."""
    return _kernel_divide(a, b) if in_kernel() else a / b


def sqrt(x: Array) -> Array:
    """``sqrt(x)``; in kernel mode through :func:`jaxquat._fusion.fusible`, its derivative reading
    the fused root (callers keep ``x`` finite and ``> 0`` where they differentiate; 0 gives 0)."""
    return _kernel_sqrt(x) if in_kernel() else jnp.sqrt(x)


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
    # A plain division in kernel mode too: atan2's own JVP differentiates it, never this value.
    ax, ay = jnp.abs(x), jnp.abs(y)
    swap = ay > ax
    num = jnp.where(swap, ax, ay)
    den = jnp.where(swap, ay, ax)
    r = atan2_of_ratio(_fusion.fusible(num / jnp.where(den == 0, 1.0, den)), swap, x)
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
