"""The torque-free rigid body in closed form (Euler-Poinsot motion).

With principal moments ``I`` and no torque, the body angular velocity is a
Jacobi elliptic function of time and the attitude follows from the conserved
spatial angular momentum plus one angle, the precession about it, which needs
the elliptic integral of the third kind (Landau and Lifshitz, Mechanics, section
37; Celledoni, Fasso, Safstrom and Zanna 2008 use the same ingredients). This
module evaluates that solution exactly (to rounding, at any time, in one step),
differentiably, for any initial state.

Conventions: ``q`` maps body to space (``v_s = q v_b q*``), ``omega`` is the
body angular velocity, ``moments`` are the principal moments (the body axes are
the principal axes; use :func:`principal_axes` for a full tensor).

Solution used (``a`` the axis the polhode circles, the largest moment when
``|L|^2 > 2 E I_mid`` and the smallest otherwise; ``c`` the other extreme; ``b``
the middle)::

    w_c = A_c cn(u),  w_b = -+ A_b sn(u),  w_a = +- A_a dn(u),   u = u_0 + lambda t
    lambda^2 = |I_a - I_b| P_c / (I_1 I_2 I_3),   m = |I_b - I_c| P_a / (|I_a - I_b| P_c)
    P_a = |2 E I_a - L^2|,  P_c = |L^2 - 2 E I_c|,  A_a^2 = P_c / (I_a |I_a - I_c|), ...

evaluated through the addition theorems in ``lambda t`` from the initial
``omega`` (so it is smooth in ``omega`` even for a pure spin about ``a``). The
attitude is ``q(t) = S Exp(psi(t) e/2) p(t)``, where ``p(t)`` is the minimal
rotation taking ``n = I w / |L|`` to the fixed body axis ``e = +-e_a``, ``S``
is constant, and

    psi(t) = |L| t / I_a + |L| (I_a - I_c) / (I_a I_c lambda) [Pi(-nu; am u) - Pi(-nu; am u_0)]
             + sign(I_c - I_a) [chi(am u) - chi(am u_0)],   nu = I_a |I_b - I_c| / (I_c |I_a - I_b|),

with ``chi(phi) = phi + atan2((k_b - k_c) sin phi cos phi, k_c cos^2 phi + k_b sin^2 phi)``,
``k_i = sqrt(I_i / |I_a - I_i|)`` (the angle between the minimal-rotation frame
and Landau's Euler-angle frame). Steady rotations about a principal axis (a
pure spin about the middle axis, a spin in the plane of two equal moments, a
spherical body, ``w = 0``) are evaluated as ``q0 Exp(w t)``. The formula and
its signs are checked against ``scipy.integrate.solve_ivp`` (DOP853, rtol 1e-13)
in ``tests/test_torque_free.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _fusion, _quaternion, _rotation, _trig
from .elliptic import (
    agm,
    am_given,
    complete_arguments,
    complete_rd,
    legendre_joint,
    partial_y,
    quarter_period,
    reduced_amplitude,
    sn_cn_dn,
)
from .inertia import validated

__all__ = ["euler_poinsot", "polhode_period"]


def _validated_moments(moments, name: str = "moments") -> Array:
    moments = _checks.vec3(moments, name)
    if not _checks.is_traced(moments):  # the diagonal tensors built in NumPy: no eager XLA operation
        m = np.asarray(moments)
        tensors = np.zeros(m.shape + (3,), m.dtype)
        tensors[..., [0, 1, 2], [0, 1, 2]] = m
        validated(tensors, name)
    return moments


def _roles(moments: list[Array], omega: list[Array]):
    """Axis indices ``(a, b, c)``: ``a`` the axis the polhode circles (the largest moment when
    ``|L|^2 > 2 E I_mid``, else the smallest), ``b`` the middle one, ``c`` the other extreme.
    ``moments`` and ``omega`` by components."""
    m0, m1, m2 = moments
    # The stable argsort's order, without a sort: the first smallest, the last largest.
    lo = jnp.where((m0 <= m1) & (m0 <= m2), 0, jnp.where(m1 <= m2, 1, 2))
    hi = jnp.where((m2 >= m1) & (m2 >= m0), 2, jnp.where(m1 >= m0, 1, 0))
    mid = 3 - lo - hi
    i_mid = _pick(moments, mid)
    # L^2 - 2 E I_mid, written as a sum of terms (no subtraction of large numbers).
    p_mid = sum(moments[i] * (moments[i] - i_mid) * (omega[i] * omega[i]) for i in range(3))
    around_largest = p_mid > 0
    a = jnp.where(around_largest, hi, lo)
    c = jnp.where(around_largest, lo, hi)
    return a, mid, c


def _pick(x: Sequence[Array], idx: Array) -> Array:
    """``x[idx]`` of components ``x`` per element, as selects: the derivative of
    ``take_along_axis`` is a scatter, and the dozen of them made ``euler_poinsot``'s gradient
    compile 25 % slower (7.0 s -> 5.5 s for a 201-time trajectory, float64, this 2-core CPU)."""
    return jnp.where(idx == 0, x[0], jnp.where(idx == 1, x[1], x[2]))


def _parameters(moments: list[Array], w: list[Array], a: Array, b: Array, c: Array):
    """Moment gaps, ``P_c``, the parameter ``m``, its complement ``1 - m`` and the rate ``lambda``
    (``moments`` and ``w`` by components).

    ``P_a, P_b, P_c`` are sums of non-negative terms (``P_b`` up to rounding),
    so ``m`` and ``1 - m`` carry full relative precision, also near the separatrix.

    The gaps are signed by the roles (``|I_a - I_b| = s (I_a - I_b)`` with ``s = +1``
    when ``a`` is the largest moment), not ``abs``: at an axisymmetric body
    (``I_b = I_c``, ``m = 0``) the derivative of ``abs`` is 0, which dropped the
    first-order effect of separating the equal moments (a silently wrong derivative);
    the signed gap continues the same formulas analytically to ``m < 0``. Likewise
    ``P_b`` is clamped at 0 in value only, so its derivative on the separatrix is that
    of the analytic formula.
    """
    ia, ib, ic = _pick(moments, a), _pick(moments, b), _pick(moments, c)
    wa, wb, wc = _pick(w, a), _pick(w, b), _pick(w, c)
    sign = jnp.where(ia > ic, 1.0, -1.0)
    dab, dac, dbc = sign * (ia - ib), sign * (ia - ic), sign * (ib - ic)
    pa = ib * dab * wb * wb + ic * dac * wc * wc
    pc = ia * dac * wa * wa + ib * dbc * wb * wb
    pb = ia * dab * wa * wa - ic * dbc * wc * wc
    pb = pb + jax.lax.stop_gradient(jnp.maximum(pb, 0.0) - pb)
    m = _fusion.fusible(dbc * pa / (dab * pc))
    mc = _fusion.fusible(dac * pb / (dab * pc))
    lam = _fusion.fusible(jnp.sqrt(dab * pc / (moments[0] * moments[1] * moments[2])))
    return dab, dac, dbc, pc, m, mc, lam


def _safe_state(moments: list[Array], omega: list[Array]):
    """Roles, the mask of states the elliptic formulas cover, and inputs made safe elsewhere (all
    by components).

    Not covered: steady rotations that are not about the polhode axis ``a``
    (``w_a = 0``) and bodies with ``I_a`` equal to another moment.
    """
    a, b, c = _roles(moments, omega)
    ia, ib, ic = _pick(moments, a), _pick(moments, b), _pick(moments, c)
    general = (_pick(omega, a) != 0) & (ia != ib) & (ia != ic)
    safe_w = [jnp.where(general, x, v) for x, v in zip(omega, (1.0, 0.5, 0.25))]
    safe_i = [jnp.where(general, x, v) for x, v in zip(moments, (1.0, 2.0, 3.0))]
    out = _fusion.one_loop_both_ways(jnp.broadcast_arrays(general, *safe_w, *safe_i, *_roles(safe_i, safe_w)))
    return out[0], list(out[1:4]), list(out[4:7]), out[7:]


class _Motion(NamedTuple):
    """What the elliptic solution needs of one body and its initial state, formed once for all
    its times (:func:`_motion`; names as in the module docstring, ``s`` the sign of ``w_a``,
    ``wb_hat = A_b sn(u_0)``, ``abs_wa = A_a dn(u_0)``). The fields from ``e`` on are vectors and a
    quaternion as tuples of their components; ``agm`` is the AGM of ``m``
    (:func:`jaxquat.mechanics.elliptic.agm`) and ``rd_complete`` ``R_D(0, 1, 1 - m)``
    (:func:`jaxquat.mechanics.elliptic.complete_rd`)."""

    m: Array
    mc: Array
    lam: Array
    amp_a: Array
    r_cb: Array  # A_c / A_b
    g: Array  # m / A_b^2
    sigma: Array
    s: Array
    wb_hat: Array
    abs_wa: Array
    dn0: Array
    wc: Array
    sn0: Array
    cn0: Array
    ell: Array  # |L|
    nu: Array
    kb: Array
    kc: Array
    ia: Array
    ic: Array
    h0: Array  # the half turns of the amplitude at time 0 (reduced_amplitude)
    rd_complete: Array
    chi0: Array
    e: tuple[Array, ...]  # the fixed body axis +-e_a, by components (as the five below)
    moments: tuple[Array, ...]
    ea: tuple[Array, ...]
    eb: tuple[Array, ...]
    ec: tuple[Array, ...]
    left: tuple[Array, ...]  # q_0 p_0*, a quaternion
    agm: tuple[tuple[Array, Array, Array], Array]
    # legendre's (s, c, y) at the amplitude at time 0 and for the complete integrals, each (2,) + B
    start: tuple[Array, Array, Array]

    def at_times(self, t: Array) -> _Motion:
        """Each field but ``start`` (kept per body) broadcast to the shape of the times ``t``
        (``batch + T``), once: reverse mode
        then sums each per-body cotangent over the times once, not at every use. With one axis of
        times (``simulate``'s case) the broadcasts are one :func:`jaxquat._fusion.spread`, whose
        cotangents are summed in one loop, not a reduction (a kernel) each: ``simulate``'s default
        gradient program (1000 bodies x 101 times) 413 -> 338 fusions, its first call 8.04-8.20 ->
        7.44-7.71 s in float32 and 8.11-8.17 -> 7.59-7.73 s in float64, later calls 97-105 -> 94-101
        ms and 248-250 -> 237-238 ms (one pinned core of a 2-core Intel Xeon, session 60)."""
        extra = (None,) * (t.ndim - self.m.ndim)
        flat, tree = jax.tree.flatten(self._replace(agm=None, start=None))  # pyright: ignore[reportArgumentType]
        agm = (tuple(x[(..., *extra)] for x in self.agm[0]), self.agm[1][(..., *extra)])
        return jax.tree.unflatten(tree, _to_times(flat, t))._replace(agm=agm, start=self.start)


def _to_times(flat: list[Array], t: Array) -> list[Array]:
    """Per-body arrays (all of one shape ``B``) broadcast to the times' shape ``B + T``; with one axis
    of times as one :func:`jaxquat._fusion.spread` (:meth:`_Motion.at_times`)."""
    extra = (None,) * (t.ndim - flat[0].ndim)
    if len(extra) == 1 and t.shape[:-1] == flat[0].shape:  # one axis of times: the cotangents in one loop
        return list(_fusion.spread(flat, t.shape[-1]))
    return [jnp.broadcast_to(x[(..., *extra)], t.shape) for x in flat]


# The per-body arrays of _motion (44) pass through one_loop in groups of at most this many, one loop
# each. One loop for all 44 compiled without vector instructions: one_loop's reduce is a loop over a
# pair inside the loop over the bodies, and LLVM unrolls it (so that the loop over the bodies is the
# innermost and is vectorised) only while the body is small. Groups of 16 are vectorised, each
# computing the shared parameters again. Measured (session 84, one core of a 2-core AMD EPYC with
# AVX-512, float32, benchmarks/simulation.py's loss, least of 7, two processes each, one loop -> groups
# of 16): 10^5 bodies x 2 times forward 46.1-48.5 -> 39.3-40.6 ms, 3-column jacfwd 94.5-99.2 ->
# 78.3-79.3 ms (the gradient 105.5 -> 102.0 ms, one jvp 73.9 -> 68.9 ms, one process each); 1000 x 101
# forward 10.87-10.90 -> 10.00-10.77 ms, gradient 25.4-26.4 -> 22.0-22.5 ms, jvp and jacfwd the same.
# The forward program has 60 fusions instead of 57, and the first eager call at 1000 x 101 (three
# fresh processes each, alternated, two cores) took 1.07-1.24 s against 1.01-1.06 s (XLA 0.77-0.89
# against 0.71-0.75 s). Groups of 11 and 22 ran within the spread of 16 (forward 43.1-46.1 ms in a
# slower hour, when one loop took 50.3-53.0 ms).
_GROUP = 16


def _motion(q0: Array, w0: list[Array], moments: list[Array], a: Array, b: Array, c: Array) -> _Motion:
    """The per-body part of the elliptic solution (states that are not steady rotations; see the
    module docstring): the parameters, the AGM of ``m``, the amplitude at time 0, the arguments of
    the integrals at time 0 and of the complete ones (``start``: :func:`_state_at` evaluates them
    in the Carlson loop of its times) and the constant left factor of ``q(t)``. ``w0`` and
    ``moments`` by components.

    Its scalars are formed in three loops over the bodies (``_fusion``, in groups of ``_GROUP``),
    and the integrals' results in another (:func:`_state_at`): XLA's CPU compiler otherwise gives each
    per-body array a kernel of its own that evaluates the roles and the parameters again (61 of
    ``simulate``'s 126 kernels on its default path, where each kernel costs about 13 ms of compiling
    even when it is small)."""
    ia, ib, ic = _pick(moments, a), _pick(moments, b), _pick(moments, c)
    wa, wb, wc = _pick(w0, a), _pick(w0, b), _pick(w0, c)
    dab, dac, dbc, pc, m, mc, lam = _parameters(moments, w0, a, b, c)
    fusible = _fusion.fusible
    amp_a = fusible(jnp.sqrt(pc / (ia * dac)))
    r_cb = fusible(jnp.sqrt(ib * dab / (ic * dac)))  # A_c / A_b
    g = fusible(dbc * ib / pc)  # m / A_b^2
    cyclic = jnp.mod(b - c, 3) == 1
    sigma = jnp.where(cyclic, 1.0, -1.0) * jnp.where(ia > ib, -1.0, 1.0)
    s = jnp.sign(wa)
    wb_hat = -sigma * s * wb  # = A_b sn(u)
    abs_wa = s * wa  # = A_a dn(u)
    dn0 = fusible(abs_wa / amp_a)
    sn0, cn0 = _unit_pair(r_cb * wb_hat, wc)
    momentum = [moments[i] * w0[i] for i in range(3)]
    ell = fusible(jnp.sqrt(momentum[0] * momentum[0] + momentum[1] * momentum[1] + momentum[2] * momentum[2]))
    nu = fusible(ia * dbc / (ic * dab))
    kb, kc = fusible(jnp.sqrt(ib / dab)), fusible(jnp.sqrt(ic / dac))
    dtype = ell.dtype
    ea, eb, ec = ([(i == k).astype(dtype) for k in range(3)] for i in (a, b, c))
    e = [s * x for x in ea]  # the fixed body axis
    p0 = _toward(momentum, e)  # takes the momentum's direction onto e
    left = _quaternion.multiply_dense(_arrays.components(q0), [p0[0], -p0[1], -p0[2], -p0[3]])
    # The amplitude at 0 as (sn, cn) from the rates (A_c cn = w_c, A_b sn = w_b_hat), not as an angle:
    # near a spin about the middle axis cn is tiny and an angle near pi/2 would lose eps / cn in the
    # integrals. One Carlson evaluation gives F and Pi at it and the complete integrals (K and
    # Pi(-nu | m)), with those at the times (_state_at); the complete ones are used for every time
    # at which the amplitude has turned.
    h0, s0, c0 = reduced_amplitude(sn0, cn0)
    chi0 = _chi(_trig.atan2(sn0, cn0), sn0, cn0, kb, kc)
    scalars = dict(m=m, mc=mc, lam=lam, amp_a=amp_a, r_cb=r_cb, g=g, sigma=sigma, s=s, wb_hat=wb_hat, abs_wa=abs_wa)
    scalars.update(dn0=dn0, wc=wc, sn0=sn0, cn0=cn0, ell=ell, nu=nu, kb=kb, kc=kc, ia=ia, ic=ic, chi0=chi0)
    scalars.update(h0=h0, s0=s0, c0=c0, y0=partial_y(c0, m, mc))
    vectors = dict(e=e, moments=moments, ea=ea, eb=eb, ec=ec, left=left)
    arrays = jnp.broadcast_arrays(*scalars.values(), *(x for v in vectors.values() for x in v))
    out = iter(x for k in range(0, len(arrays), _GROUP) for x in _fusion.one_loop_both_ways(arrays[k : k + _GROUP]))
    fields: dict[str, Any] = {name: next(out) for name in scalars}
    fields.update({name: tuple(next(out) for _ in v) for name, v in vectors.items()})
    m, mc = fields["m"], fields["mc"]
    s0, c0, y0 = (fields.pop(name) for name in ("s0", "c0", "y0"))  # used here only
    # The integrals at the amplitude at time 0 and the complete ones (K and Pi(-nu | m)) are taken
    # with those at the times, in one Carlson loop (_state_at).
    sk, ck, yk = complete_arguments(mc)
    start = (jnp.stack([s0, sk]), jnp.stack([c0, ck]), jnp.stack([y0, yk]))
    fields.update(rd_complete=complete_rd(mc))
    return _Motion(**fields, agm=jax.lax.stop_gradient(agm(m, mc)), start=start)


def _chi(phi: Array, sn: Array, cn: Array, kb: Array, kc: Array) -> Array:
    """The angle between the minimal-rotation frame and Landau's Euler-angle frame, plus ``phi``."""
    return phi + _trig.atan2((kb - kc) * sn * cn, kc * cn * cn + kb * sn * sn)


def _state_at(body: _Motion, t: Array) -> tuple[list[Array], list[Array]]:
    """The elliptic solution at times ``t`` (shaped ``B + T``) from the per-body part ``body``."""
    k = body.at_times(t)
    m, mc, lam, s, sigma, ell, ia, ic = k.m, k.mc, k.lam, k.s, k.sigma, k.ell, k.ia, k.ic
    r_cb, wb_hat, wc, sn0, cn0, dn0 = k.r_cb, k.wb_hat, k.wc, k.sn0, k.cn0, k.dn0
    # Angular velocity by the addition theorems in v = lambda t (smooth at a pure spin about a).
    # den = 1 - m sn0^2 sn_v^2, written as a sum of non-negative terms: near a spin about
    # the middle axis both products tend to 1 and the difference lost eps / den (1.5e-3
    # relative in float32 at t = 10 from w0 = (1e-6, 1, 1e-6), I = (1, 2, 3)).
    # Each group of scalars below is computed in one loop, values and cotangents (_fusion): XLA's
    # CPU compiler otherwise copies their producers (the AGM amplitude, Carlson's integrals) into
    # every consumer. Measured (one body, 11 times, float64, one core, XLA's defaults): the
    # compile of the value 2.8 -> 2.3 s, of its gradient 12.3 -> 8.5 s, of jacfwd 8.4 -> 6.3 s;
    # 1000 bodies x 101 times, float32 / float64: value 137 / 245 -> 118 / 226 ms, gradient
    # 870 / 2174 -> 803 / 2047 ms.
    sn_v, cn_v, dn_v = _fusion.one_loop_both_ways(
        jnp.broadcast_arrays(*sn_cn_dn(am_given(lam * t, m, mc, k.rd_complete, *k.agm), m, mc))
    )
    den = cn0 * cn0 + sn0 * sn0 * dn_v * dn_v
    wc_t = (wc * cn_v - r_cb * wb_hat * dn0 * sn_v * dn_v) / den
    wb_hat_t = (wb_hat * cn_v * dn_v + wc * dn0 * sn_v / r_cb) / den
    abs_wa_t = (k.abs_wa * dn_v - k.g * k.amp_a * wb_hat * wc * sn_v * cn_v / r_cb) / den
    wc_t, wb_hat_t, abs_wa_t = _fusion.one_loop_both_ways(jnp.broadcast_arrays(wc_t, wb_hat_t, abs_wa_t))

    # Precession angle about the angular momentum; the amplitude at t again as (sn, cn) from the
    # rates, the whole number of turns from ``a_N u``.
    snt, cnt = _fusion.one_loop_both_ways(_unit_pair(r_cb * wb_hat_t, wc_t))
    theta_t = _trig.atan2(snt, cnt)
    ht, st, ct = _fusion.one_loop_both_ways(jnp.broadcast_arrays(*reduced_amplitude(snt, cnt)))
    # The whole turns: am(u) and pi u / (2 K) = a_N u (a_N the AGM's limit) both lie in the same
    # quarter turn between multiples of K, so they differ by less than pi / 2 and the rounding
    # keeps a margin of a quarter turn; a second Landen descent per time (the unwrapped amplitude)
    # gave the same integers for a fifth more of the forward pass.
    # One Carlson loop for Pi at the times and, per body, F and Pi at time 0 and the complete ones.
    (f, pi), (_, pi_part) = legendre_joint((*body.start, -body.nu[None]), (st, ct, partial_y(ct, m, mc), -k.nu))
    # The whole turns of the amplitude at t come from am(u0 + lambda t), u0 = F(am u0) = 2 h0 K + F(r0)
    # (only rounded, so formed without derivatives).
    sg = jax.lax.stop_gradient
    u0 = sg(body.h0 * jnp.pi / body.agm[1] + f[0])
    pi_full, pi0, u0 = _to_times(list(_fusion.one_loop_both_ways((pi[1], 2 * body.h0 * pi[1] + pi[0], u0))), t)
    turns = jnp.round(sg(k.agm[1] * (u0 + lam * t) - theta_t) / (2 * jnp.pi))
    pi_t = 2 * (2 * turns + ht) * pi_full + pi_part
    psi = (
        ell * t / ia
        + ell * (ia - ic) / (ia * ic * lam) * (pi_t - pi0)
        + jnp.sign(ic - ia) * (_chi(2 * jnp.pi * turns + theta_t, snt, cnt, k.kb, k.kc) - k.chi0)
    )
    (psi,) = _fusion.one_loop_both_ways((psi,))
    return _attitude(k, psi, s * abs_wa_t, -sigma * s * wb_hat_t, wc_t)


def _attitude(k: _Motion, psi: Array, wa: Array, wb: Array, wc: Array) -> tuple[list[Array], list[Array]]:
    """The components of ``q = left Exp(psi e / 2) p`` and of ``w`` from the precession angle and
    the rates about the axes ``a, b, c`` (:func:`propagate` computes them in one loop).

    ``p`` is the minimal rotation taking the direction of ``n = I w`` onto ``e``: ``(|n| + n.e, n x
    e)`` normalised, whose norm squared is ``2 |n| (|n| + n.e)``. Since ``e = sign(w_a) e_a``,
    ``n.e = I_a |w_a| >= 0``, so ``n`` is never opposite ``e`` and the scalar part is
    positive (the general :func:`jaxquat._rotation.minimal_rotation` handles both).
    Written on components, the vector and quaternion forms' gradient compiled into a dozen loops
    over ``(..., 3)`` and ``(..., 4)`` elements, each evaluating the shared work again."""
    ea, eb, ec, e, moments = k.ea, k.eb, k.ec, k.e, k.moments
    w = [wa * ea[i] + wb * eb[i] + wc * ec[i] for i in range(3)]
    p = _toward([moments[i] * w[i] for i in range(3)], e, k.ell)  # |I w| = |L| at every time
    sin_half, cos_half = _trig.sincos(psi / 2)
    r = [cos_half] + [x * sin_half for x in e]
    return _quaternion.multiply_dense(_quaternion.multiply_dense(list(k.left), r), p), w


def _toward(n: Sequence[Array], e: Sequence[Array], norm: Array | None = None) -> list[Array]:
    """The components of the minimal rotation taking the direction of ``n`` onto the unit ``e``,
    for ``n.e >= 0``: ``(|n| + n.e, n x e)`` normalised (its norm squared is ``2 |n| (|n| +
    n.e)``). The same for every positive scale of ``n``, so the callers pass the momentum ``I w``
    itself, not ``I w / |L|`` (three divisions fewer per body and per time: ``simulate``'s default
    path, 1000 bodies x 101 times, one pinned core of a 2-core Intel Xeon, first call 2.59-2.61 ->
    2.50-2.52 s in float32 and 2.66-2.68 -> 2.52-2.55 s in float64, the call 55 -> 51-52 ms in
    float64, the gradient 1-3 % less; session 60). Its range is that of ``|L|``, whose square
    ``_motion`` forms as well, within a factor of 2 (``2 |n| (|n| + n.e) <= 4 |L|^2``).

    ``norm``, where given, is ``|n|`` known beforehand: :func:`_attitude` passes the conserved
    ``|L|`` (``|I w(t)| = |L|`` at every time), which saves a square root per time and two of
    ``simulate``'s kernels; the result is unit to rounding and its derivatives are the same
    function's."""
    if norm is None:
        norm = _fusion.fusible(jnp.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]))
    scalar = norm + (n[0] * e[0] + n[1] * e[1] + n[2] * e[2])
    inv = _fusion.fusible(jax.lax.rsqrt(2 * norm * scalar))
    cross = (n[1] * e[2] - n[2] * e[1], n[2] * e[0] - n[0] * e[2], n[0] * e[1] - n[1] * e[0])
    return [scalar * inv] + [x * inv for x in cross]


def _unit_pair(y: Array, x: Array) -> tuple[Array, Array]:
    """``(y, x) / hypot(y, x)``: the sine and cosine of ``atan2(y, x)`` without the angle;
    ``(0, 1)`` with zero derivative at ``(0, 0)`` (a pure spin about the polhode axis)."""
    r2 = y * y + x * x
    zero = r2 == 0
    inv = _fusion.fusible(jax.lax.rsqrt(jnp.where(zero, 1.0, r2)))
    return jnp.where(zero, 0.0, y * inv), jnp.where(zero, 1.0, x * inv)


def propagate(q0: Array, omega0: Array, moments: Array, t: Array) -> tuple[Array, Array]:
    """:func:`euler_poinsot` without argument checks: ``q0``, ``omega0`` and ``moments`` broadcast to
    one batch shape ``B``, ``t`` shaped ``B + T`` (``T`` the times per body, possibly ``()``); the
    results are shaped ``B + T``. The per-body part of the solution (:func:`_motion`) is formed once
    for all ``T`` times.

    :func:`euler_poinsot` calls it compiled as one program (``_arrays.compiled``): an eager first
    call at 11 times took 6.0 s as 214 single-operation compilations, 3.0 s compiled whole; a
    repeated eager call 0.77 s, now 5 ms.
    Forming the per-body part once instead of at every time (``simulate``'s default path, 1000
    bodies x 101 saved times, this 2-core CPU): a call 31-39 ms against 96-99 ms in float32, 60
    against 207 ms in float64 (the loops of the AGM and of one Carlson evaluation run per body;
    ``docs/benchmarks.md``). Session 47 made the per-time part cheaper (one Landen descent, Carlson's
    ``R_C`` vectorised, the attitude on components): 16-18 ms and 31-37 ms, the gradient 76-79 and
    143-152 ms (``docs/integrators.md``, "The closed form's derivatives"). Since session 64 the
    per-body integrals share the Carlson loop of the times (:func:`jaxquat.mechanics.elliptic.legendre_joint`):
    one pinned core of a 2-core AMD EPYC, two fresh processes each, the same program before and
    after: the first eager call 2.22-2.33 -> 1.99-2.07 s in float32 and 2.25-2.29 -> 2.13-2.20 s in
    float64, the first gradient (compile and run) 7.26-7.27 -> 5.49-5.76 s and 7.40-7.62 -> 5.72-6.33
    s, later calls 18.7-18.9 -> 15.6-16.4 ms and 40.3-40.6 -> 39.2-39.3 ms, gradients 83.8-87.0 ->
    76.4-78.2 ms and 188-193 -> 184-190 ms. Since session 65 its divisions and square roots with
    several users pass through :func:`jaxquat._fusion.fusible`, so XLA fuses them into their
    consumers' loops: 71 -> 47 kernels, the first call 1.42 -> 1.12-1.25 s on both cores (the
    figures are in that function's docstring)."""
    times = (None,) * (t.ndim - (q0.ndim - 1))
    general, safe_w, safe_i, roles = _safe_state(_arrays.components(moments), _arrays.components(omega0))
    q_gen, w_gen = _state_at(_motion(q0, safe_w, safe_i, *roles), t)
    # The steady rotation q0 Exp(w0 t) and the selects on components, in the one loop of the rest.
    # q0 and w0 reach the times through _to_times, so that reverse mode sums their seven cotangents
    # over the times in one loop. Broadcast by indexing, each was summed by a reduce of its own, and
    # XLA's CPU compiler handed those and the cotangent of omega0's rows to YNNPACK as one fusion:
    # 10.4 ms of the gradient at 10^5 bodies x 2 times (float32, one core), whose whole took
    # 99.8-102.3 ms, now 87.3-89.6 ms (two processes each); at 1000 x 101 the gradient program
    # 201 -> 190 fusions (the gradient 21.8-23.2 -> 22.5-23.3 ms; session 84).
    per_time = _to_times([*_arrays.components(q0), *_arrays.components(omega0)], t)
    q0c, w0, general = per_time[:4], per_time[4:], general[(..., *times)]
    q_steady = _quaternion.multiply_dense(q0c, _rotation.exp_components([x * t for x in w0]))
    out = _fusion.one_loop_both_ways(
        jnp.broadcast_arrays(*(jnp.where(general, a, b) for a, b in zip(q_gen + w_gen, q_steady + w0)))
    )
    return _arrays.assemble(*out[:4]), _arrays.assemble(*out[4:])


def euler_poinsot(
    q0: Float[ArrayLike, "*#batch 4"],
    omega0: Float[ArrayLike, "*#batch 3"],
    moments: Float[ArrayLike, "*#batch 3"],
    t: Float[ArrayLike, "*#batch"],
) -> tuple[Float[Array, "*batch 4"], Float[Array, "*batch 3"]]:
    """Exact attitude and body angular velocity of a torque-free rigid body at time ``t``.

    Solves Euler's equations ``I w' = (I w) x w`` (Chou (1992) eq. (82) with zero
    torque; Schwab (2002) eq. (26)) with ``q' = q (0, w) / 2`` (Chou eq. (20)) in
    closed form, for principal moments ``moments`` in any order, from
    ``(q0, omega0)`` at time 0 (``t`` may be negative). ``q0`` is assumed unit;
    the result is unit to rounding. All arguments broadcast over leading axes
    (``t`` has no trailing axis): pass ``t`` shaped ``(n,)`` with one body to
    get a trajectory. Cost, independent of ``t``: per body one AGM and two Carlson
    ``R_F``/``R_J`` evaluations (the integrals at time 0 and the complete ones), per time
    one Landen descent and one Carlson evaluation, all Carlson evaluations in one loop; error about ``eps * lambda t``
    in the phase. Near the separatrix (``|L|^2 = 2 E I_mid``) the elliptic
    parameter tends to 1 and the formulas stay accurate: the complementary
    parameter is formed without cancellation, and the amplitudes enter the
    precession integral as ``(sn, cn)`` taken from the rates, not as angles (from
    ``w0 = (p, 1, p)``, ``I = (1, 2, 3)``, ``p = 1e-3 .. 1e-14``, the attitude at
    ``t = 10`` agrees with DOP853 to 1e-13 rad in float64 and 1.2e-5 in float32).
    Differentiable in every argument, in both modes, including bodies with two
    equal moments and states on the separatrix (the amplitude's derivative in
    ``m`` is the regular Carlson form, see :mod:`jaxquat.mechanics.elliptic`). Within ``p``
    of a spin about the middle axis the derivative carries a relative error of
    about ``eps / p`` (measured 1e-11 to 2e-10 at ``p = 1e-6`` in float64). Exactly at a steady spin
    about the middle axis, or about an axis in a plane of equal moments, the
    derivative is that of the steady rotation ``q0 Exp(w t)``, which omits the
    linearised precession: the limit of nearby derivatives differs there.
    See the module docstring for the formulas.

    Args:
        q0: attitude at time 0 ``(..., 4)`` (body to space, unit).
        omega0: body angular velocity at time 0 ``(..., 3)``, in principal axes.
        moments: principal moments of inertia ``(..., 3)``, positive, in any order.
        t: times ``(...)`` (no trailing axis), any sign.

    Returns:
        ``(q, omega)``: the attitude ``(..., 4)`` and the body angular velocity ``(..., 3)`` at
        ``t``, the batch axes of all four arguments broadcast.
    """
    moments = _validated_moments(moments)
    q0, omega0, moments, t = _checks.arguments(
        q0=(q0, "quaternion"), omega0=(omega0, "vector"), moments=(moments, "vector"), t=(t, "scalar")
    )
    dtype = q0.dtype
    work = _checks.working_dtype(dtype)
    q, w = _arrays.compiled(propagate, *(x.astype(work) for x in (q0, omega0, moments, t)))
    return q.astype(dtype), w.astype(dtype)


def polhode_period(
    omega0: Float[ArrayLike, "*#batch 3"], moments: Float[ArrayLike, "*#batch 3"]
) -> Float[Array, "*batch"]:
    """Period ``4 K(m) / lambda`` of the body angular velocity of a torque-free body.

    For a body spinning near its intermediate axis this is twice the
    Dzhanibekov flip interval ``2 K(m) / lambda`` (the body flips twice per
    period). Infinite on the separatrix; ``inf`` for steady rotations.
    Notation as :func:`euler_poinsot` (Landau and Lifshitz, section 37).
    """
    moments = _validated_moments(moments)
    omega0, moments = _checks.arguments(omega0=(omega0, "vector"), moments=(moments, "vector"))
    dtype = omega0.dtype
    work = _checks.working_dtype(dtype)
    return _arrays.compiled(_polhode_period, omega0.astype(work), moments.astype(work)).astype(dtype)


def _polhode_period(omega0: Array, moments: Array) -> Array:
    general, safe_w, safe_i, roles = _safe_state(_arrays.components(moments), _arrays.components(omega0))
    *_, m, mc, lam = _parameters(safe_i, safe_w, *roles)
    period = 4 * quarter_period(m, mc) / lam
    return jnp.where(general & (mc > 0), period, jnp.inf)
