"""The vectorisable sin/cos/atan2 of ``jaxquat._trig`` against libm (numpy, float64).

Every rotation op that takes an angle goes through these, so they are held to a few
units in the last place on large samples, across the range reduction's quadrants,
at the signed zeros and axes of atan2, and in their derivatives.
"""

import json
import os
import pathlib
import platform
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from jax.test_util import check_grads

from helpers import DTYPE, NP_DTYPE, X64, seeds, xla_fuses_multiply_add
from jaxquat import _trig

EPS = float(np.finfo(NP_DTYPE).eps)
N = 200_000
_sincos = jax.jit(_trig.sincos)
_atan2 = jax.jit(_trig.atan2)


def _ulps(got, want, eps=EPS):
    """Error in units of eps times max(1, |want|) (absolute near zero, relative elsewhere)."""
    got = np.asarray(got, np.float64)
    return np.max(np.abs(got - want) / np.maximum(np.abs(want), 1.0)) / eps


@pytest.mark.parametrize("scale", [1.0, 10.0, 1e3, 1e5])
def test_sincos_within_two_ulps_of_libm(scale):
    x = np.random.default_rng(0).uniform(-scale, scale, N).astype(NP_DTYPE)
    s, c = _sincos(jnp.asarray(x))
    x64 = x.astype(np.float64)
    assert _ulps(s, np.sin(x64)) < 2.0
    assert _ulps(c, np.cos(x64)) < 2.0


def test_sincos_small_arguments_are_relatively_exact():
    # sin x = x to rounding for tiny x, where an absolute bound would be too weak
    x = np.geomspace(1e-30, 1e-2, 2000).astype(NP_DTYPE)
    x = np.concatenate([x, -x, [0.0]]).astype(NP_DTYPE)
    s, c = _sincos(jnp.asarray(x))
    want = np.sin(x.astype(np.float64))
    rel = np.abs(np.asarray(s, np.float64) - want) / np.maximum(np.abs(want), 1e-300)
    assert np.max(rel[x != 0]) < 2 * EPS
    assert np.asarray(s)[-1] == 0.0 and np.asarray(c)[-1] == 1.0


def test_sincos_at_quadrant_boundaries():
    k = np.arange(-64, 65)
    x = np.concatenate([k * np.pi / 4, k * np.pi / 2 + 1e-3, k * np.pi / 2 - 1e-3]).astype(NP_DTYPE)
    s, c = _sincos(jnp.asarray(x))
    x64 = x.astype(np.float64)
    assert _ulps(s, np.sin(x64)) < 2.0
    assert _ulps(c, np.cos(x64)) < 2.0


def test_atan2_within_three_ulps_of_libm():
    rng = np.random.default_rng(1)
    y = (rng.standard_normal(N) * 10.0 ** rng.uniform(-6, 6, N)).astype(NP_DTYPE)
    x = (rng.standard_normal(N) * 10.0 ** rng.uniform(-6, 6, N)).astype(NP_DTYPE)
    got = _atan2(jnp.asarray(y), jnp.asarray(x))
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    rel = np.abs(np.asarray(got, np.float64) - want) / np.maximum(np.abs(want), np.finfo(NP_DTYPE).tiny)
    assert np.max(rel) < 3 * EPS


def test_atan2_axes_and_signed_zeros_match_numpy():
    pz, nz, one = 0.0, -0.0, 1.0
    y = np.array([pz, nz, pz, nz, one, -one, pz, nz, one, -one, one, -one, np.inf, one], NP_DTYPE)
    x = np.array([pz, pz, nz, nz, pz, pz, one, one, -one, -one, one, -one, one, np.inf], NP_DTYPE)
    got = np.asarray(_atan2(jnp.asarray(y), jnp.asarray(x)))
    want = np.arctan2(y, x)
    np.testing.assert_allclose(got, want, rtol=3 * EPS, atol=0)
    np.testing.assert_array_equal(np.signbit(got), np.signbit(want))


@given(seed=seeds)
def test_identities(seed):
    x = jax.random.uniform(jax.random.PRNGKey(seed), (64,), DTYPE, -20.0, 20.0)
    s, c = _sincos(x)
    np.testing.assert_allclose(s * s + c * c, 1.0, atol=4 * EPS)
    # atan2(sin x, cos x) is x wrapped into (-pi, pi]
    wrapped = np.remainder(np.asarray(x, np.float64) + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(np.asarray(_atan2(s, c), np.float64), wrapped, atol=64 * EPS)


def test_gradients():
    """``check_grads`` and the identities on jitted functions: eager, their first and second
    derivatives ran as about 110 single-operation compilations (3.0 s of the float32 pass,
    session 41)."""
    x = jnp.asarray([-7.0, -1.2, 0.0, 0.3, 2.0, 1e4], DTYPE)
    sincos, atan2 = jax.jit(_trig.sincos), jax.jit(_trig.atan2)
    check_grads(sincos, (x,), order=2, modes=["fwd", "rev"], eps=1e-3 if DTYPE == jnp.float32 else 1e-5)
    y = jnp.asarray([0.3, -2.0, 7.0, 0.0, -0.2], DTYPE)  # (off the branch cut at x < 0, y = 0)
    xx = jnp.asarray([-1.0, 0.5, -3.0, 2.0, -1.0], DTYPE)
    check_grads(atan2, (y, xx), order=2, modes=["fwd", "rev"], eps=1e-3 if DTYPE == jnp.float32 else 1e-5)
    # exact derivative identities, not finite differences
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(_trig.sin)))(x), jax.jit(_trig.cos)(x), rtol=0, atol=0)
    gy, gx = jax.jit(jax.vmap(jax.grad(_trig.atan2, argnums=(0, 1))))(y, xx)
    np.testing.assert_allclose(gy, xx / (xx * xx + y * y), rtol=4 * EPS)
    np.testing.assert_allclose(gx, -y / (xx * xx + y * y), rtol=4 * EPS)


def test_jit_vmap_and_batch_shapes():
    x = jnp.linspace(-3, 3, 12, dtype=DTYPE).reshape(3, 4)
    s, c = jax.vmap(_trig.sincos)(x)
    np.testing.assert_allclose(s, jnp.sin(x), atol=4 * EPS)
    np.testing.assert_allclose(c, jnp.cos(x), atol=4 * EPS)
    assert _atan2(x, x[::-1]).shape == (3, 4)
    assert _trig.sin(jnp.asarray(0.5, DTYPE)).shape == ()


@pytest.mark.parametrize("cpu", [True, False], ids=["cpu", "other"])
def test_the_polynomials_and_barriers_are_for_cpu_only(cpu, monkeypatch):
    """With the CPU backend the rotation ops use these polynomials and the optimisation
    barriers of ``_arrays.scalars`` (no libm calls); with any other (the backend test patched,
    so no GPU is needed) XLA's own sine, cosine and atan2 and no barrier, to the same values."""
    import jaxquat as jq

    monkeypatch.setattr(_trig, "_cpu", lambda: cpu)
    q = jnp.asarray(np.random.default_rng(0).normal(size=(64, 4)), DTYPE)
    r = jnp.asarray(np.random.default_rng(1).normal(size=(64, 3)), DTYPE)
    # fresh lambdas: jit's trace cache is keyed by the function, and the other case traced it too
    texts = [
        jax.jit(lambda x, f=fn: f(x)).trace(x).lower().as_text() for fn, x in ((jq.to_rotvec, q), (jq.from_rotvec, r))
    ]
    transcendental = any(op in t for t in texts for op in ("stablehlo.atan2", "stablehlo.sine", "stablehlo.cosine"))
    barrier = any("optimization_barrier" in t for t in texts)
    assert transcendental == (not cpu) and barrier == cpu
    # fresh traces again, against numpy's libm in float64
    rv = jax.jit(lambda x: jq.to_rotvec(x))(q)
    qq = jax.jit(lambda x: jq.from_rotvec(x))(r)
    qn = np.asarray(q, np.float64) / np.linalg.norm(np.asarray(q, np.float64), axis=-1, keepdims=True)
    qn = qn * np.sign(qn[:, :1])
    vec = np.linalg.norm(qn[:, 1:], axis=-1, keepdims=True)
    want_rv = qn[:, 1:] / vec * 2 * np.arctan2(vec, qn[:, :1])
    rn = np.asarray(r, np.float64)
    th = np.linalg.norm(rn, axis=-1, keepdims=True)
    want_q = np.concatenate([np.cos(th / 2), np.sin(th / 2) * rn / th], -1)
    tol = 1e-12 if DTYPE == jnp.float64 else 2e-6
    np.testing.assert_allclose(np.asarray(rv), want_rv, atol=tol * 10)
    np.testing.assert_allclose(np.asarray(qq), want_q, atol=tol)


def _ulp_error(got, want, dtype=NP_DTYPE):
    """Error in units in the last place of ``want`` (in ``dtype``), ``want`` exact in float64 or
    long double."""
    got = np.asarray(got).astype(np.longdouble)
    return np.max(np.abs(got - want) / np.spacing(np.abs(want).astype(dtype)).astype(np.longdouble))


def test_reciprocal_rsqrt_and_kernel_sqrt_accuracy():
    """``reciprocal`` and the kernel-mode ``sqrt`` are correctly rounded (one IEEE operation each
    through ``_fusion.fusible``: measured 0.5 ulp, bound 0.75 for the reference's own rounding),
    ``rsqrt`` two of them (``1 / sqrt``: within 2 ulp by construction, measured 1.46 in float64
    and 1.48 in float32), over the exponent range where ``1 / y`` is normal, both signs for the
    reciprocal. Until session 65 they were Newton's iterations from a bit-pattern guess (0.5, 0.99
    and 1.7 ulp with fused multiply-adds, 1.24, 1.21 and 1.76 without, on a smaller range);
    ``test_trig_bounds_without_fused_multiply_add`` still runs the case without them."""
    errors = _kernel_op_errors(NP_DTYPE, xla_fuses_multiply_add())
    assert errors["reciprocal"] <= 0.75
    assert errors["rsqrt"] <= 2.0
    assert errors["sqrt"] <= 0.75
    assert not _trig.in_kernel()


def _kernel_op_errors(dtype, fused: bool) -> dict:
    """The ulp errors of ``reciprocal`` (both signs), ``rsqrt`` and the kernel-mode ``sqrt`` in
    ``dtype`` on ``N`` arguments from the bottom of the normal range to ``2^125`` (float64:
    ``2^1021``) where XLA fuses multiply-adds, to ``2^64`` (``2^512``) where it does not."""
    info = np.finfo(dtype)
    top = info.maxexp - 4 if fused else info.maxexp // 2
    rng = np.random.default_rng(4)
    e = rng.uniform(np.log2(info.tiny) + 1, top, N)  # 2^-126 < x (float64: 2^-1022)
    x = jnp.asarray((rng.uniform(1.0, 2.0, N) * 2.0**e).astype(dtype))
    exact = np.asarray(x).astype(np.longdouble)
    reciprocal = jax.jit(_trig.reciprocal)
    with _trig.kernel_mode():
        root = jax.jit(lambda x: _trig.sqrt(x))(x)  # a fresh function: traced in kernel mode
    return dict(
        reciprocal=max(_ulp_error(reciprocal(x), 1 / exact, dtype), _ulp_error(reciprocal(-x), -1 / exact, dtype)),
        rsqrt=_ulp_error(jax.jit(_trig.rsqrt)(x), 1 / np.sqrt(exact), dtype),
        sqrt=_ulp_error(root, np.sqrt(exact), dtype),
    )


_WITHOUT_FMA = """
import json, numpy as np, jax, jax.numpy as jnp
from jaxquat import _trig
from helpers import xla_fuses_multiply_add
from test_trig import N, _kernel_op_errors, _ulps
out = {"fused": xla_fuses_multiply_add()}
for dt in (np.float32, np.float64):
    a = np.random.default_rng(0).uniform(-1e5, 1e5, N).astype(dt)
    s, c = jax.jit(_trig.sincos)(jnp.asarray(a))
    a64, eps = a.astype(np.float64), np.finfo(dt).eps
    errors = dict(_kernel_op_errors(dt, False), sincos=max(_ulps(s, np.sin(a64), eps), _ulps(c, np.cos(a64), eps)))
    out[np.dtype(dt).name] = {name: float(err) for name, err in errors.items()}
print(json.dumps(out))
"""


@pytest.mark.skipif(not X64, reason="one subprocess checks both dtypes: run in the float64 pass")
@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="XLA's ISA cap is x86-64's")
def test_trig_bounds_without_fused_multiply_add():
    """The bounds of the tests above on a CPU without FMA, as XLA compiles for one when limited
    to AVX (``--xla_cpu_max_isa=AVX``, a fresh interpreter), arguments from the bottom of the normal
    range to ``2^64`` (float32; ``2^512`` in float64: the reciprocal's range without FMA):
    ``reciprocal`` within 1.5 ulp (correctly rounded since session 65: 0.5; Newton's 1.24 before),
    ``rsqrt`` 2 (1.21 before), the kernel-mode square root 3 (0.5; 1.76 before), ``sin`` and
    ``cos`` on ``|x| <= 1e5`` 2 (0.76 in float32, where the range reduction's
    second product rounded before session 58: 8.0 ulp). The probe of
    ``helpers.xla_fuses_multiply_add`` must say no."""
    env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " --xla_cpu_max_isa=AVX").strip())
    env["JAX_ENABLE_X64"] = "1"
    env["PYTHONPATH"] = os.pathsep.join([str(pathlib.Path(__file__).parent), env.get("PYTHONPATH", "")])
    done = subprocess.run([sys.executable, "-c", _WITHOUT_FMA], env=env, capture_output=True, text=True, check=True)
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["fused"] is False, out
    for dtype in ("float32", "float64"):
        got = out[dtype]
        assert got["reciprocal"] <= 1.5 and got["rsqrt"] <= 2.0 and got["sqrt"] <= 3.0, out
        assert got["sincos"] < 2.0, out


def test_reciprocal_and_rsqrt_special_values():
    """Exact at powers of two (where Newton's ``r (2 - y r)`` once stopped an ulp short), NaN in
    NaN out, zero square root 0 in kernel mode; float16 kept; derivatives ``-1/y^2`` and ``-1/(2
    x^1.5)`` to second order."""
    k = np.arange(-60, 61)
    powers = jnp.asarray(2.0**k, DTYPE)
    np.testing.assert_array_equal(_trig.reciprocal(powers), jnp.asarray(2.0 ** (-k), DTYPE))
    np.testing.assert_array_equal(_trig.reciprocal(-powers), jnp.asarray(-(2.0 ** (-k)), DTYPE))
    even = jnp.asarray(4.0 ** np.arange(-30, 31), DTYPE)
    np.testing.assert_array_equal(_trig.rsqrt(even), jnp.asarray(2.0 ** (-np.arange(-30, 31)), DTYPE))
    nan = jnp.asarray([np.nan], DTYPE)
    assert np.isnan(_trig.reciprocal(nan)).all() and np.isnan(_trig.rsqrt(nan)).all()
    with _trig.kernel_mode():
        assert float(_trig.sqrt(jnp.zeros((), DTYPE))) == 0.0
    half = _trig.reciprocal(jnp.asarray([3.0, -0.5], jnp.float16))
    assert half.dtype == jnp.float16
    np.testing.assert_allclose(np.asarray(half, np.float64), [1 / 3, -2.0], rtol=1e-3)
    x = jnp.asarray([0.3, 1.7, 12.0], DTYPE)
    check_grads(_trig.reciprocal, (x,), order=2, modes=("fwd", "rev"), eps=1e-3, atol=1e-2, rtol=1e-2)
    check_grads(_trig.rsqrt, (x,), order=2, modes=("fwd", "rev"), eps=1e-3, atol=1e-2, rtol=1e-2)
