"""The exact torque-free propagator (Euler-Poinsot): against Landau's elliptic-function
solution written here with scipy.special.ellipj, the symmetric top in closed form, a tight
DOP853 reference (forward and backward in time, any ordering of the moments), conserved
quantities, the flow property over t = 1000, the Dzhanibekov flip interval, every
degenerate state, gradients, batching and bad input. Also principal_axes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp
from hypothesis import given

import jaxquat as jq
from helpers import DTYPE, X64, assert_close, assert_same_rotation, dop853_reference, random_inertias, seeds

TOL = 1e-11 if X64 else 2e-4
Q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
_euler_poinsot = jax.jit(jq.euler_poinsot)
_PAD = 64


def _propagate(q0, w0, moments, t):
    """``jq.euler_poinsot`` on its arguments broadcast together, flattened to one batch and padded
    to a multiple of ``_PAD`` entries (repeating the last), then cut and shaped back: the value
    tests share one compiled program (two with the flip test's 24001 times) where each shape
    compiled its own, about 1.2 s each (float64, 2-core EPYC), before session 36. Broadcasting
    itself is tested by ``test_jit_vmap_nested_batching_and_dtype``, on the function as it is."""
    q0, w0, moments, t = (np.asarray(a) for a in (q0, w0, moments, t))
    batch = np.broadcast_shapes(q0.shape[:-1], w0.shape[:-1], moments.shape[:-1], t.shape)
    n = int(np.prod(batch))
    size = -(-n // _PAD) * _PAD

    def flat(a, tail):
        a = np.broadcast_to(a, batch + tail).reshape((n, *tail))
        return jnp.asarray(np.concatenate([a, np.broadcast_to(a[-1:], (size - n, *tail))]))

    q, w = _euler_poinsot(flat(q0, (4,)), flat(w0, (3,)), flat(moments, (3,)), flat(t, ()))
    return tuple(jnp.asarray(np.asarray(v)[:n].reshape(batch + v.shape[1:])) for v in (q, w))


def _flat(*args):
    return jnp.concatenate(jq.euler_poinsot(*args))


def _random_bodies(seed, n):
    rng = np.random.default_rng(seed)
    moments = np.sort(rng.uniform(0.5, 3.0, (n, 3)), axis=-1)
    moments[:, 2] = np.minimum(moments[:, 2], 0.95 * (moments[:, 0] + moments[:, 1]))  # triangle inequality
    moments = np.array([rng.permutation(m) for m in moments])
    q0 = rng.normal(size=(n, 4))
    return q0 / np.linalg.norm(q0, axis=-1, keepdims=True), rng.normal(size=(n, 3)), moments


def test_angular_velocity_against_landau_with_scipy_ellipj():
    """I1 < I2 < I3, L^2 > 2 E I2 (Landau and Lifshitz, Mechanics, eq. 37.10):
    w1 = sqrt((2E I3 - L^2) / (I1 (I3 - I1))) cn(tau), w2 = ... sn(tau), w3 = ... dn(tau),
    tau = t sqrt((I3 - I2)(L^2 - 2E I1) / (I1 I2 I3)), from an initial state on the tau = 0 line."""
    i1, i2, i3 = 1.0, 2.0, 3.0
    w_init = np.array([0.4, 0.0, 0.9])  # at tau = 0: sn = 0, cn = dn = 1
    e2 = np.sum(np.array([i1, i2, i3]) * w_init**2)
    l2 = np.sum((np.array([i1, i2, i3]) * w_init) ** 2)
    assert l2 > e2 * i2
    tau_rate = np.sqrt((i3 - i2) * (l2 - e2 * i1) / (i1 * i2 * i3))
    m = (i2 - i1) * (e2 * i3 - l2) / ((i3 - i2) * (l2 - e2 * i1))
    ts = np.linspace(0.0, 40.0, 33)
    sn, cn, dn, _ = sp.ellipj(tau_rate * ts, m)
    ref = np.stack(
        [
            np.sqrt((e2 * i3 - l2) / (i1 * (i3 - i1))) * cn,
            np.sqrt((e2 * i3 - l2) / (i2 * (i3 - i2))) * sn,
            np.sqrt((l2 - e2 * i1) / (i3 * (i3 - i1))) * dn,
        ],
        axis=-1,
    )
    # Landau's signs put w2 and w3 with the same sign for this branch (I1 w1' = (I2 - I3) w2 w3 < 0
    # while cn decreases): our propagator must reproduce them from the initial state alone.
    _, w = _propagate(
        jnp.asarray(Q0, DTYPE), jnp.asarray(w_init, DTYPE), jnp.asarray([i1, i2, i3], DTYPE), jnp.asarray(ts, DTYPE)
    )
    assert_close(w, ref, tol=TOL, what="w(t) vs Landau")
    # Period 4K(m)/tau_rate.
    period = jq.polhode_period(jnp.asarray(w_init, DTYPE), jnp.asarray([i1, i2, i3], DTYPE))
    assert_close(period, 4 * sp.ellipk(m) / tau_rate, tol=TOL * 10, what="period")


def test_symmetric_top_closed_form():
    """I1 = I2: w3 constant, (w1, w2) turns at Omega = (I3 - I1) w3 / I1 in the body;
    the attitude is q(t) = exp(L_hat |L| t / (2 I1)) q0 exp(-e3 Omega t / 2) (space precession
    about L at |L|/I1, body spin about e3 at -Omega relative to it)."""
    i1, i3 = 1.5, 2.5
    w0 = np.array([0.3, -0.7, 1.1])
    ts = np.linspace(-5.0, 30.0, 15)
    q, w = _propagate(
        jnp.asarray(Q0, DTYPE), jnp.asarray(w0, DTYPE), jnp.asarray([i1, i1, i3], DTYPE), jnp.asarray(ts, DTYPE)
    )
    om = (i3 - i1) * w0[2] / i1
    c, s = np.cos(om * ts), np.sin(om * ts)
    w_ref = np.stack([c * w0[0] - s * w0[1], s * w0[0] + c * w0[1], np.full_like(ts, w0[2])], -1)
    assert_close(w, w_ref, tol=TOL, what="symmetric-top w")
    l_space = np.asarray(jq.rotate(jnp.asarray(Q0), jnp.asarray(np.array([i1, i1, i3]) * w0)), np.float64)
    precess = np.asarray(jq.from_rotvec(jnp.asarray(l_space[None] * ts[:, None] / i1)))
    spin = np.asarray(jq.from_rotvec(jnp.asarray(np.outer(-om * ts, [0.0, 0.0, 1.0]))))
    q_ref = np.asarray(jq.multiply(jq.multiply(jnp.asarray(precess), jnp.asarray(Q0)), jnp.asarray(spin)))
    assert_same_rotation(q, q_ref, tol=TOL)


@pytest.mark.skipif(not X64, reason="a 1e-13 reference needs float64; float32 is checked by the conservation test")
@pytest.mark.parametrize("seed", [0, 1])
def test_against_dop853_any_order_both_directions(seed):
    q0, w0, moments = _random_bodies(seed, 4)
    ts = np.linspace(0.0, 25.0, 6)
    for sign in (1.0, -1.0):
        for k in range(4):
            q_ref, w_ref = dop853_reference(q0[k], w0[k], moments[k], sign * ts)
            q, w = _propagate(jnp.asarray(q0[k]), jnp.asarray(w0[k]), jnp.asarray(moments[k]), jnp.asarray(sign * ts))
            assert_same_rotation(q, q_ref, tol=2e-11)
            assert_close(w, w_ref, tol=2e-11, what=f"w body {k} sign {sign}")


_ALL = (0, 1, 2, 3)


# One compiled pair of Jacobians (d/d q0, omega0, moments, t; forward and reverse) and one compiled
# set of central differences serve every derivative test in this module.
def _columns(jacobians):
    return jnp.concatenate([j if j.ndim == 2 else j[:, None] for j in jacobians], axis=1)


_jacobians = jax.jit(
    lambda q0, w, m, t: (
        _columns(jax.jacfwd(_flat, argnums=_ALL)(q0, w, m, t)),
        _columns(jax.jacrev(_flat, argnums=_ALL)(q0, w, m, t)),
    )
)


@jax.jit
def _central_differences(q0, w, m, t, eps):
    """Columns d/d q0, omega0, moments, t of the flat state, by central differences."""
    steps = eps * jnp.eye(11, dtype=w.dtype)
    f = jax.vmap(lambda d: _flat(q0 + d[:4], w + d[4:7], m + d[7:10], t + d[10]))
    return ((f(steps) - f(-steps)) / (2 * eps)).T


def _check_against_differences(w0, moments, t=5.0, *, eps, tol):
    args = tuple(jnp.asarray(a) for a in (Q0, w0, moments, t))
    ref = _central_differences(*args, eps)
    for got, mode in zip(_jacobians(*args), ("fwd", "rev")):
        assert np.all(np.isfinite(got)), mode
        assert_close(got, ref, tol=tol, what=f"{mode} at omega0 = {w0}, moments = {moments}")


DEGENERATE = {
    "spin about the largest axis": ([0.0, 0.0, 2.0], [1.0, 2.0, 3.0]),
    "spin about the smallest axis": ([1.3, 0.0, 0.0], [1.0, 2.0, 3.0]),
    "spin about the middle axis": ([0.0, 1.0, 0.0], [1.0, 2.0, 3.0]),
    "at rest": ([0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
    "symmetric, I1 = I2": ([0.3, 0.4, 1.0], [1.0, 1.0, 2.0]),
    "symmetric, I2 = I3": ([0.3, 0.4, 1.0], [1.0, 2.0, 2.0]),
    "spherical": ([0.3, 0.4, 1.0], [2.0, 2.0, 2.0]),
    "spin in the plane of equal moments": ([0.3, 0.4, 0.0], [2.0, 2.0, 3.0]),
    "near the separatrix": ([np.sqrt(3.0) * 0.5 + 1e-7, 0.3, 0.5], [1.0, 2.0, 3.0]),
}


@pytest.mark.skipif(not X64, reason="a 1e-13 reference needs float64")
@pytest.mark.parametrize("case", sorted(DEGENERATE))
def test_degenerate_states(case):
    w0, moments = (np.asarray(v) for v in DEGENERATE[case])
    ts = np.array([0.0, 0.7, 5.0, 20.0])
    q_ref, w_ref = dop853_reference(Q0, w0, moments, ts)
    q, w = _propagate(jnp.asarray(Q0), jnp.asarray(w0), jnp.asarray(moments), jnp.asarray(ts))
    assert_same_rotation(q, q_ref, tol=2e-11)
    assert_close(w, w_ref, tol=2e-11, what=case)
    jac, jac_rev = _jacobians(jnp.asarray(Q0), jnp.asarray(w0), jnp.asarray(moments), jnp.asarray(5.0))
    assert np.all(np.isfinite(jac)) and np.all(np.isfinite(jac_rev))
    assert_close(jac, jac_rev, tol=1e-9 * max(1.0, float(np.abs(jac).max())), what="forward == reverse")


@pytest.mark.parametrize("moments", ([1.0, 2.0, 3.0], [2.0, 2.5, 4.0]))
def test_near_a_spin_about_the_middle_axis_against_dop853(moments):
    """The (p, m) neighbourhood of the Dzhanibekov spin: w0 = (p, 1, +-p) for p = 1e-3 ..
    1e-14 (1 - m ~ p^2), to t = 10, against DOP853. The amplitudes enter the precession
    integral as (sn, cn) from the rates; as angles near pi/2 they lost eps / cn0, which
    gave 3e-2 rad at p = 1e-14 (now 9e-14 rad in float64)."""
    ps = 10.0 ** -np.array([3.0, 6.0, 9.0, 12.0, 14.0])
    w0 = np.array([[p, 1.0, sign * p] for p in ps for sign in (1.0, -1.0)])
    ts = np.array([0.0, 2.5, 5.0, 10.0])
    q, w = _propagate(jnp.asarray(Q0), jnp.asarray(w0)[:, None], jnp.asarray(moments), jnp.asarray(ts))
    for k in range(len(w0)):
        q_ref, w_ref = dop853_reference(Q0, w0[k], moments, ts)
        # float32: the precession integrals are ~30 here and carry ~30 ulps (measured 1.2e-5).
        assert_same_rotation(q[k], q_ref, tol=2e-11 if X64 else 5e-5)
        assert_close(w[k], w_ref, tol=2e-11 if X64 else 5e-5, what=f"w, w0 = {w0[k]}")


def _rk4_state(w0, moments, t, n=20000):
    """Independent reference for derivatives: classical RK4 on the raw 7-state ODE in JAX
    (dt = t / n; halving dt changes its Jacobians by < 2e-11)."""

    def rhs(y):
        q, w = y[:4], y[4:]
        qd = 0.5 * jnp.concatenate([-(q[1:] @ w)[None], q[0] * w + jnp.cross(q[1:], w)])
        return jnp.concatenate([qd, jnp.cross(moments * w, w) / moments])

    h = t / n

    def step(y, _):
        k1 = rhs(y)
        k2 = rhs(y + h / 2 * k1)
        k3 = rhs(y + h / 2 * k2)
        return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + rhs(y + h * k3)), None

    y, _ = jax.lax.scan(step, jnp.concatenate([jnp.asarray(Q0), w0]), None, length=n)
    return y


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_derivatives_at_equal_moments_near_the_middle_axis_and_on_the_separatrix():
    """Where the derivative was silently wrong or NaN, against independent references.

    * Axisymmetric bodies, d/d moments: the gap |I_b - I_c| was formed with abs, whose
      derivative 0 at the tie dropped the first-order effect (error 0.43 before).
    * w0 = (1e-6, 1, 1e-6), I = (1, 2, 3), d/d omega0 to t = 10 (entries up to 280, the
      saddle's growth): against the RK4 reference (error 1.3e-4 before, 9e-10 now).
    * On the separatrix (I = (3, 4, 6), w0 = (2, 0.5, 1)) and 1e-9 either side: NaN before
      (through simulate: tests/test_integrators.py::test_forward_mode_through_simulate).
    * A zero initial rate about the axis ``c`` (w0 = (1, 2, 0) and (0.5, 0.5, 0), where ``c`` is
      the largest axis, and (0, 2, 1), where it is the smallest): the amplitude at time 0 is a
      quarter turn, ``cos = 0``, where the elliptic integrals' derivative in ``cos^2`` is
      infinite. NaN in both modes before session 77; the integrals are now differentiated in
      ``cos`` (``elliptic._carlson_unit_z``).

    All at t = 5 from Q0, through the jitted Jacobians the degenerate-state test compiles.
    """
    for moments in ([1.0, 2.0, 2.0], [3.0, 4.0, 4.0]):
        _check_against_differences([0.4, -0.3, 0.9], moments, eps=1e-6, tol=1e-8)
    for shift in (0.0, 1e-9, -1e-9):
        _check_against_differences([2.0, 0.5 + shift, 1.0], [3.0, 4.0, 6.0], eps=1e-6, tol=3e-8)  # measured 5e-9
    for w0 in ([1.0, 2.0, 0.0], [0.5, 0.5, 0.0], [0.0, 2.0, 1.0]):
        _check_against_differences(w0, [1.0, 2.0, 3.0], eps=1e-6, tol=1e-8)  # measured 2.6e-9
    # Near the saddle the parametrisation (u0 ~ log(1/p), d u0 / d omega0 ~ 1/p) costs
    # about eps / p relative in the derivative (2e-10 at p = 1e-6; measured 1e-11 with XLA's default
    # code and 2.3e-10 with LLVM optimisation off), hence the bound 2e-9.
    w0, moments = jnp.asarray([1e-6, 1.0, 1e-6]), jnp.asarray([1.0, 2.0, 3.0])
    ref = jax.jit(jax.jacfwd(_rk4_state))(w0, moments, 5.0)
    fwd, rev = _jacobians(jnp.asarray(Q0), w0, moments, jnp.asarray(5.0))
    scale = float(np.abs(ref).max())
    for got, mode in ((fwd[:, 4:7], "fwd"), (rev[:, 4:7], "rev")):
        assert_close(got / scale, ref / scale, tol=2e-9, what=f"near the middle axis ({mode})")


@pytest.mark.skipif(X64, reason="half precision does not depend on the x64 flag: checked once, in the float32 pass")
@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_computes_in_float32_and_returns_the_input_dtype(dtype):
    """euler_poinsot, polhode_period, principal_axes and the elliptic functions in float16 and
    bfloat16 (non-finite or NotImplementedError before): the input dtype out, and the float32
    answer rounded to it."""
    w0, moments, t = np.array([0.3, 1.0, 0.2]), np.array([1.0, 2.0, 3.0]), np.array([0.5, 3.0])
    inertia = np.array([[2.0, 0.1, 0.0], [0.1, 1.5, 0.0], [0.0, 0.0, 1.0]])
    calls = {
        "euler_poinsot": lambda d: jq.euler_poinsot(
            jnp.asarray(Q0, d), jnp.asarray(w0, d), jnp.asarray(moments, d), jnp.asarray(t, d)
        ),
        "polhode_period": lambda d: jq.polhode_period(jnp.asarray(w0, d), jnp.asarray(moments, d)),
        "principal_axes": lambda d: jq.principal_axes(jnp.asarray(inertia, d)),
        "ellipj": lambda d: jq.ellipj(jnp.asarray(t, d), jnp.asarray([0.5, 0.99], d)),
        "ellipk": lambda d: jq.ellipk(jnp.asarray([0.5, 0.99], d)),
    }
    for name, call in calls.items():
        outs, refs = jax.tree_util.tree_leaves(call(dtype)), jax.tree_util.tree_leaves(call(jnp.float32))
        for o, r in zip(outs, refs):
            assert o.dtype == dtype, f"{name}: {o.dtype}"
            o, r = np.asarray(o, np.float32), np.asarray(r, np.float32)
            assert np.all(np.isfinite(o)), name
            if name == "principal_axes" and o.shape[-1] == 4:  # q and -q are one rotation
                o = o * np.sign(np.sum(o * r))
            # the inputs themselves are rounded to 3 significant digits: 0.05 relative, amplified a little
            assert_close(o, r, tol=0.05 * max(1.0, float(np.abs(r).max())), what=f"{name} {dtype}")


@given(seeds)
def test_conserved_quantities(seed):
    """|q| = 1, energy, body |L| and spatial L = q (I w) q* conserved at random times up to 1000."""
    q0, w0, moments = _random_bodies(seed, 16)
    t = np.random.default_rng(seed).uniform(-1000, 1000, 16)
    args = [jnp.asarray(v, DTYPE) for v in (q0, w0, moments, t)]
    q, w = _propagate(*args)
    q, w = np.asarray(q, np.float64), np.asarray(w, np.float64)
    tol = 1e-12 if X64 else 2e-5
    assert_close(np.linalg.norm(q, axis=-1), np.ones(16), tol=tol * 10, what="|q|")
    e0, e1 = (moments * w0**2).sum(-1), (moments * w**2).sum(-1)
    assert_close(e1 / e0, np.ones(16), tol=tol * 100, what="energy")
    l0 = np.asarray(jq.rotate(jnp.asarray(q0), jnp.asarray(moments * w0)))
    l1 = np.asarray(jq.rotate(jnp.asarray(q), jnp.asarray(moments * w)))
    # float32: the phase at t ~ 1000 carries eps * lambda t, but the invariants do not depend on it.
    assert_close(l1, l0, tol=tol * 100 * np.abs(l0).max(), what="spatial angular momentum")


@pytest.mark.skipif(not X64, reason="the 1e-11 rad bar is a float64 bar")
def test_flow_property_to_t_1000():
    """The issue's bar problem (I = diag(1,2,3), w0 = (1, 0.1, 0.5)): one evaluation at
    t = 1000 equals 100 successive evaluations over 10 (a different path through the formulas:
    different phases, different numbers of whole periods), within 1e-11 rad."""
    moments, w0 = jnp.asarray([1.0, 2.0, 3.0]), jnp.asarray([1.0, 0.1, 0.5])
    q_direct, w_direct = _propagate(jnp.asarray([1.0, 0, 0, 0]), w0, moments, jnp.asarray(1000.0))

    def step(carry, _):
        q, w = carry
        return jq.euler_poinsot(q, w, moments, 10.0), None

    (q_steps, w_steps), _ = jax.lax.scan(step, (jnp.asarray([1.0, 0, 0, 0]), w0), None, length=100)
    assert float(jq.angle_between(q_direct, q_steps)) < 1e-11
    assert_close(w_direct, w_steps, tol=1e-11, what="w")


def test_dzhanibekov_flip_interval():
    """A body spun near its intermediate axis flips every 2K(m)/lambda: the sign changes of
    w_2 from the propagator are spaced by half of polhode_period, which equals scipy's
    2 ellipk(m)/lambda computed here from the initial state."""
    moments = np.array([1.0, 2.0, 3.0])
    w0 = np.array([0.01, 2.0, 0.01])
    ts = np.linspace(0.0, 120.0, 24001)
    _, w = _propagate(
        jnp.asarray(Q0, DTYPE), jnp.asarray(w0, DTYPE), jnp.asarray(moments, DTYPE), jnp.asarray(ts, DTYPE)
    )
    w2 = np.asarray(w[:, 1], np.float64)
    idx = np.nonzero(np.sign(w2[1:]) != np.sign(w2[:-1]))[0]
    crossings = ts[idx] - w2[idx] * (ts[idx + 1] - ts[idx]) / (w2[idx + 1] - w2[idx])
    spacing = np.diff(crossings)
    e2, l2 = (moments * w0**2).sum(), ((moments * w0) ** 2).sum()
    around_largest = l2 > e2 * moments[1]
    ia, ic = (moments[2], moments[0]) if around_largest else (moments[0], moments[2])
    pc, pa = abs(l2 - e2 * ic), abs(e2 * ia - l2)
    lam = np.sqrt(abs(ia - moments[1]) * pc / moments.prod())
    m = abs(moments[1] - ic) * pa / (abs(ia - moments[1]) * pc)
    flip = 2 * sp.ellipk(m) / lam
    assert len(spacing) >= 3
    assert_close(spacing / flip, np.ones_like(spacing), tol=1e-6 if X64 else 1e-3, what="flip interval")
    period = float(jq.polhode_period(jnp.asarray(w0, DTYPE), jnp.asarray(moments, DTYPE)))
    # 1e-11: the reference forms m by differences, the library by sums of positive terms.
    assert abs(period / (2 * flip) - 1) < (1e-11 if X64 else 1e-5)


@pytest.mark.skipif(not X64, reason="finite differences need float64")
def test_gradients_match_finite_differences():
    """Reverse and forward mode against central differences, in q0, omega0, moments and t,
    at a generic state, a pure spin about the largest axis, and a body at rest (moments
    (1, 2, 2.5): diag(1, 2, 3) sits on the triangle inequality, which a finite-difference
    step in the moments would cross)."""
    for w0 in ([1.0, 0.1, 0.5], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]):
        _check_against_differences(w0, [1.0, 2.0, 2.5], 3.0, eps=1e-6, tol=1e-6)


def test_jit_vmap_nested_batching_and_dtype():
    """``_PAD`` bodies, so that the flat call is the padded value tests' compiled program (12
    bodies compiled one more of its own: 2.2-2.6 s in float64, 1.8 s in float32, session 41)."""
    q0, w0, moments = _random_bodies(11, _PAD)
    t = np.linspace(-3, 9, _PAD)
    args = [jnp.asarray(v, DTYPE) for v in (q0, w0, moments, t)]
    eager = _euler_poinsot(*args)
    mapped = jax.jit(jax.vmap(jq.euler_poinsot))(*args)
    nested = _euler_poinsot(*[a.reshape((8, _PAD // 8) + a.shape[1:]) for a in args])
    for e, m_, n_ in zip(eager, mapped, nested):
        assert e.dtype == DTYPE
        assert_close(m_, e, tol=TOL, what="vmap")
        assert_close(n_.reshape(e.shape), e, tol=TOL, what="nested")
    # One body, many times: t broadcasts against the batch.
    q, w = _euler_poinsot(args[0][0], args[1][0], args[2][0], args[3])
    assert q.shape == (_PAD, 4) and w.shape == (_PAD, 3)


def test_bad_input():
    with pytest.raises(ValueError, match=r"argument 'q0' must be a quaternion array shaped \(\.\.\., 4\)"):
        jq.euler_poinsot(jnp.ones(3), jnp.ones(3), jnp.ones(3), 1.0)
    with pytest.raises(ValueError, match=r"argument 'moments' must be a 3-vector array shaped \(\.\.\., 3\)"):
        jq.euler_poinsot(jnp.asarray(Q0), jnp.ones(3), jnp.ones(4), 1.0)
    with pytest.raises(ValueError, match="moments"):
        jq.euler_poinsot(jnp.asarray(Q0), jnp.ones(3), jnp.asarray([1.0, 1.0, 5.0]), 1.0)  # triangle inequality
    with pytest.raises(TypeError, match="argument 't'"):
        jq.euler_poinsot(jnp.asarray(Q0), jnp.ones(3), jnp.ones(3), jnp.ones(2, jnp.int32))


def test_principal_axes():
    inertia = random_inertias(3, 8, np.float64)
    moments, q_axes = jq.principal_axes(jnp.asarray(inertia, DTYPE))
    r = np.asarray(jq.to_matrix(q_axes), np.float64)
    rebuilt = r @ (np.asarray(moments, np.float64)[..., None] * np.swapaxes(r, -1, -2))
    assert_close(rebuilt, inertia, tol=1e-12 if X64 else 1e-5, what="R diag R^T")
    assert np.all(np.diff(np.asarray(moments), axis=-1) >= 0)
    assert_close(np.linalg.det(r), np.ones(8), tol=1e-12 if X64 else 1e-5, what="det")
    ref_moments = np.linalg.eigvalsh(inertia)
    assert_close(moments, ref_moments, tol=1e-12 if X64 else 1e-5, what="moments vs numpy")


@pytest.mark.skipif(not X64, reason="a 1e-13 reference needs float64")
def test_full_tensor_through_principal_axes():
    """A body with a full inertia tensor: rotate to principal axes, propagate, rotate back;
    compare with DOP853 on Euler's equations with the full tensor."""
    from scipy.integrate import solve_ivp

    inertia = random_inertias(4, 1, np.float64)[0]
    w0 = np.array([0.4, -1.0, 0.3])
    moments, q_axes = jq.principal_axes(jnp.asarray(inertia))
    r = np.asarray(jq.to_matrix(q_axes))
    q_p, w_p = jq.euler_poinsot(
        jq.multiply(jnp.asarray(Q0), q_axes), jnp.asarray(r.T @ w0), moments, jnp.asarray([4.0])
    )
    q_body = jq.multiply(q_p, jq.conjugate(q_axes))
    w_body = np.asarray(w_p) @ r.T

    def rhs(t, y):
        q, w = y[:4], y[4:]
        qd = 0.5 * np.array([-q[1:] @ w, *(q[0] * w + np.cross(q[1:], w))])
        return np.concatenate([qd, np.linalg.solve(inertia, np.cross(inertia @ w, w))])

    sol = solve_ivp(rhs, (0, 4.0), np.concatenate([Q0, w0]), method="DOP853", rtol=1e-13, atol=1e-13)
    assert_same_rotation(q_body, sol.y[:4, -1][None], tol=1e-11)
    assert_close(w_body, sol.y[4:, -1][None], tol=1e-11, what="w")
