"""The rigid body's Lie solvers in struct-of-arrays form: the scan path of ``simulate``, and the step
that the Lie solvers of :mod:`jaxquat.integration.lie_solvers` take on a rigid-body model
(:func:`lie_step`: its error estimate and dense output too).

A batch of ``n`` bodies is carried as seven arrays ``(n,)``, one per component of ``(q, w_b)``,
instead of ``(n, 4)`` and ``(n, 3)``, and one Runge-Kutta-Munthe-Kaas step (the same method as
:class:`jaxquat.RKMK4` / :class:`jaxquat.LieEuler`: ``q_(n+1) = q_n Exp(theta_1)``,
``theta' = dexp^-1_theta(w_b)``, Euler's equations ``w_b' = I^-1 (M_b - w_b x I w_b)``) is
written out component by component, its stages unrolled. Every operation is then element-wise
over contiguous arrays: XLA fuses a step into a few loops over the batch (one per stage, through
:mod:`jaxquat._fusion`; left to itself XLA's CPU compiler made one loop per output component,
each evaluating most of the step again: :func:`rkmk_step`), and reverse mode transposes
element-wise operations into element-wise operations. In the row form
(``(n, 4)`` arrays) the transposes of the minor-axis slices, stacks and cross products become
many separate kernels (the backward step compiled to 175 fusions against the forward's 24).

Measured (torque-free bodies, batch 1000, 1000 steps, float32, this 2-core CPU, the setup of
``benchmarks/simulation.py``): the row form's forward pass 85 ms and gradient 1008 ms (11.8x);
this form 67 ms and 174 ms (2.6x). Writing only the Lie part (Exp, ``dexp^-1``, the product) in
components and leaving Euler's equations in the row form gave 82 ms and 559 ms (6.8x): the whole
step has to be element-wise. The stages are unrolled Python code (a ``fori_loop`` over stages
would carry and index a stage array).

Hand-written (not a library) because the gain is the layout itself: jaxquat's public kernels
take ``(..., 4)`` rows, and ``vmap`` of a one-body step with the batch axis last does not keep
it last (the batching rules of ``concatenate``/``stack`` move it first; measured 240 ms
forward and 1331 ms gradient).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple, cast

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .. import _arrays, _fusion, _quaternion, _rates, _rotation, _safe, _trig
from .fixed_step import scan_steps

Comps = tuple[Array, ...]


def split(x: Array) -> Comps:
    """The components of ``x`` along its last axis: ``(..., k)`` to ``k`` arrays ``(...)``."""
    return tuple(x[..., i] for i in range(x.shape[-1]))


def stack(c: Sequence[Array]) -> Array:
    """The inverse of :func:`split`."""
    return jnp.stack(list(c), axis=-1)


def _weighted(terms: Sequence[tuple[float, Comps]], scale: Any = 1.0) -> Comps:
    """``scale * sum_j coef_j v_j`` (terms with a zero coefficient skipped). The increments are
    summed before anything is added to the state (as the row form's ``tensordot`` did): adding
    each stage's small increment to ``w`` in turn rounds at ``w``'s scale once per stage, which
    doubled the median float32 error at T = 10 in ``benchmarks/simulation.py`` (1.1e-5 rad
    against 5.2e-6)."""
    out = None
    for coef, v in terms:
        if coef == 0.0:
            continue
        scaled = [coef * x for x in v]
        out = scaled if out is None else [a + b for a, b in zip(out, scaled)]
    if out is None:
        raise ValueError("an empty combination")
    return tuple(scale * x for x in out)


def _grouped(barrier: Callable, groups: Sequence[Comps]) -> list[Comps]:
    """``groups`` passed through one :mod:`jaxquat._fusion` barrier together (one loop for all),
    split back."""
    flat = barrier([x for g in groups for x in g])
    out = []
    for g in groups:
        out.append(tuple(flat[: len(g)]))
        flat = flat[len(g) :]
    return out


def _paired(barrier: Callable, a: Comps, b: Comps) -> tuple[Comps, Comps]:
    """``a`` and ``b`` through one barrier (:func:`_grouped`)."""
    a, b = _grouped(barrier, [a, b])
    return a, b


def _add(a: Comps, b: Comps) -> Comps:
    return tuple(x + y for x, y in zip(a, b))


def _recomputed(xs: Comps, recompute: bool) -> Comps:
    """``xs`` unchanged; with ``recompute``, each through :func:`jaxquat._fusion.fusible`, so that
    XLA on CPU computes them again inside every loop that reads them instead of writing them out.

    For the values a stage of the scan path's step shares between two loops in reverse mode: the
    backward pass evaluates the step again (it is rematerialised), and each stage's increments
    ``theta_i``, ``z_i``, the products ``I w`` and the cross products of Euler's equations and of
    ``dexp^-1`` are read by that stage's loop and by the loop of the cotangents. XLA (jaxlib
    0.10.2, either emitter) gives a chain of cheap operations that two loops read a kernel of its
    own: 27 of the 37 kernels of the torque-free RKMK4 backward step. Ending the chain in
    ``fusible`` makes it a cheap producer that XLA copies into both loops: the backward step in
    10 kernels, the gradient's program 99 -> 72 (the gradient of one step, 8 bodies: 32 -> 14,
    ``tests/test_integrators.py``). The same operations and values (to the bit there, and for
    1000 bodies x 1000 steps).
    Measured on ``simulate``'s scan path (1000 bodies x 1000 RKMK4 steps, one core of a 2-core
    Intel Xeon, least of 11 or 21 in each process, processes alternated): torque-free float32
    gradient 26.6-27.9 -> 24.8-26.6 ms (five processes each), float64 59.7-60.2 -> 56.0-57.5 ms
    (three), with a PD torque float64 165-166 -> 162 ms; at 10^5 bodies (least of 3) float32 4.67
    -> 4.22 s and float64 9.55 -> 8.56 s. The forward pass is the same program; one ``jvp`` 1-3 %
    slower (float64 24.7-25.3 -> 24.8-26.1 ms). Not in :func:`lie_step` (the Lie solvers in
    ``diffeqsolve``): its backward step, compiled from diffrax's checkpointed loop, kept its 120
    kernels and its gradient took 75 -> 87 ms (float32)."""
    return tuple(_fusion.fusible(x) for x in xs) if recompute else xs


def cross(a: Comps, b: Comps) -> Comps:
    """``a x b``."""
    return tuple(_rates.cross_parts(a, b))


def multiply(p: Comps, q: Comps) -> Comps:
    """The Hamilton product ``p q`` (scalar first)."""
    return tuple(_quaternion.multiply_dense(p, q))


def exp(theta: Comps, branches: str = "derivatives by batch") -> Comps:
    """``Exp(theta) = (cos(|theta|/2), sin(|theta|/2) theta/|theta|)`` (the series near 0, as
    :func:`jaxquat.from_rotvec`: finite derivatives of every order at ``theta = 0``).
    ``branches`` (:func:`jaxquat._rotation.exp_components`): a step's ``theta`` is nearly always
    below the series' switch, so by default the derivatives skip the direct branch when the whole
    batch can (a ``lax.cond``). A step compiled as a few loops on CPU chooses per exponential
    (:func:`_branches`); a batch split between devices chooses per element all the same
    (:func:`jaxquat._safe._small_batch_parts`)."""
    return tuple(_rotation.exp_components(theta, branches))


def dexpinv(theta: Comps, w: Comps, order: int, recompute: bool = False) -> Comps:
    """``J_r(theta)^-1 w`` truncated for an RKMK method of ``order`` (the series of
    :func:`jaxquat.integration.lie_solvers.dexpinv`); ``recompute``: the cross products through
    :func:`_recomputed`."""
    if order <= 1:
        return w
    c1 = _recomputed(cross(theta, w), recompute)
    if order == 2:
        return tuple(wi + 0.5 * a for wi, a in zip(w, c1))
    t2 = theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2] if order >= 5 else None
    coef = _safe.jacobian_inverse_coeff_truncated(order, t2)
    c2 = _recomputed(cross(theta, c1), recompute)
    return tuple(wi + 0.5 * a + coef * b for wi, a, b in zip(w, c1, c2))


def unit(q: Comps) -> Comps:
    """One Newton step towards ``|q| = 1``, ``q (3 - |q|^2)/2`` (as the Lie solvers end each step)."""
    scale = 1.5 - 0.5 * (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return tuple(scale * x for x in q)


# A symmetric 3x3 matrix's six entries (row, column), and the place of each of the nine among them.
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
_OF_NINE = tuple(_UPPER.index((min(i, j), max(i, j))) for i in range(3) for j in range(3))


class EulerEquations:
    """``w_b' = I^-1 (M_b - w_b x I w_b)`` in components. ``inertia`` ``(3, 3)`` (shared) or
    ``(n, 3, 3)`` (per body); ``diagonal``: only its diagonal is read (a concrete diagonal
    tensor). ``torque``: ``fn(t, q (..., 4), w (..., 3), args) -> (..., 3)`` body torque on the
    stacked rows (already vmapped over a batch), or None; with ``columns``, on the components
    stacked along the first axis, ``fn(t, q (4, n), w (3, n), args) -> (3, n)`` (a one-body law
    vmapped over the last axis).

    The inertia's entries (:meth:`entries`) are what a step hands :meth:`with_entries` after its
    input barrier: their cotangents then come out of the step's backward loop per body, and only
    their sum over the batch is taken after it. Read directly, each entry's gradient was a
    reduction of its own over the whole backward step, which XLA's CPU fusion emitters
    (jaxlib 0.10.2, its default) compiled into code that re-evaluates the step's subgraphs once
    per use: the gradient of 10 bodies x 1000 RKMK4 steps with respect to a full tensor took
    34.8 s (8.9 s before session 43; 14 ms with the older emitters), 8.8 ms now.

    A full tensor is read as its symmetric part ``(I + I^T) / 2`` (the same tensor, to the bit,
    if symmetric), as the six distinct entries of it and of its inverse: 12 entries, not 18,
    whose cotangents come out of a loop of their own (:func:`_inputs`). The stages' share of a
    gradient with respect to a full tensor is then symmetric, ``(G + G^T) / 2`` of the nine
    entries' ``G`` (the same derivative along any symmetric change). 1000 bodies x 1000 RKMK4
    steps, the gradient with respect to a traced full tensor, one core, least of 5: torque-free,
    float32, 18 entries in the state's loop 214 ms (the gradient in the initial rates: 24 ms), 12
    entries 97 ms, 12 in a loop of their own 38 ms, 15 (the tensor's nine) in a loop of their own
    122 ms; float64 369 -> 83 ms; with the PD law 299 -> 91 ms (float64 542 -> 213 ms); the first
    gradient compiled in 1.9 s instead of 3.2 s (float32, torque-free). XLA's CPU fusion did not
    fuse the cotangents of 18 entries into the state's loop and wrote each out as a kernel of its
    own that evaluated the backward step again."""

    def __init__(self, inertia: Array, torque: Callable | None, diagonal: bool, columns: bool = False):
        self.torque = torque
        self.diagonal = diagonal
        self.columns = columns
        if diagonal:
            m = jnp.diagonal(inertia, axis1=-2, axis2=-1)
            self._inertia, self._inverse = m, 1 / m
        else:  # its symmetric part (the same tensor, if symmetric: x + x and a half of it are exact)
            sym = 0.5 * (inertia + jnp.swapaxes(inertia, -1, -2))
            self._inertia, self._inverse = sym, _arrays.symmetric_inverse(sym)
        self._entries: Comps | None = None
        self._recompute = False

    def entries(self) -> Comps:
        """The arrays this reads: the moments and their inverses (diagonal), or the six distinct
        entries of the tensor's symmetric part and of its inverse (``_UPPER``'s order). Taken
        inside the step: read once before the loop they were 18 scalar arrays, each a kernel
        XLA's CPU backend compiled on its own (the first RKMK4 ``simulate`` of 1000 bodies,
        float32: 41 kernels and 0.44 s of XLA compilation, against 24 and 0.37 s; a call
        unchanged, bit for bit)."""
        if self._entries is not None:
            return self._entries
        if self.diagonal:
            return split(self._inertia) + split(self._inverse)
        return tuple(m[..., i, j] for m in (self._inertia, self._inverse) for i, j in _UPPER)

    def with_entries(self, entries: Comps, recompute: bool = False) -> EulerEquations:
        """A copy that reads ``entries`` (:meth:`entries`' layout, any broadcastable shapes);
        ``recompute``: ``I w`` and ``w x I w`` through :func:`_recomputed` (the scan path's step)."""
        new = copy.copy(self)
        new._entries = tuple(entries)
        new._recompute = recompute
        return new

    @staticmethod
    def _apply(m: Comps, v: Comps) -> Comps:
        """``m v`` for a symmetric matrix given as its six distinct entries (``_UPPER``)."""
        e = [m[k] for k in _OF_NINE]
        return tuple(e[3 * i] * v[0] + e[3 * i + 1] * v[1] + e[3 * i + 2] * v[2] for i in range(3))

    def acceleration(self, w: Comps, torque: Comps | None) -> Comps:
        """``I^-1 (M - w x I w)`` for the body torque ``M`` (None: 0)."""
        e = self.entries()
        half = len(e) // 2  # the tensor's entries, then its inverse's
        h = tuple(m * x for m, x in zip(e[:half], w)) if self.diagonal else self._apply(e[:half], w)
        h = _recomputed(h, self._recompute)
        gyro = _recomputed(cross(w, h), self._recompute)
        rhs = tuple(-g for g in gyro) if torque is None else tuple(m - g for m, g in zip(torque, gyro))
        if self.diagonal:
            return tuple(r * x for r, x in zip(e[half:], rhs))
        return self._apply(e[half:], rhs)

    def __call__(self, t, q: Comps, w: Comps, args) -> Comps:
        """The acceleration at a stage ``(q, w)``. With a torque, the stage's seven components are
        computed in one loop, values and cotangents (:func:`jaxquat._fusion.one_loop_both_ways`),
        then stacked into the rows the torque takes, and its value split into components likewise:
        XLA on CPU would otherwise copy the stage's computation into every component of the rows
        and the torque's work into every use of its components (and, in reverse mode, the whole
        backward step into each cotangent). Measured (1000 bodies x 1000 RKMK4 steps, the PD law
        ``-k_p sign(q_w) q_v - k_d w``, float32, one core of this 2-core EPYC, median of 7): the
        forward pass 19 ms, the gradient 84 ms, one ``jvp`` 42 ms; the rows formed as
        ``sum_i c_i e_i^T`` and the columns taken by products with the identity (the form before)
        274 ms, 459 ms and 377 ms; with the torque's components fused forward only, a gradient of
        603 ms, and with the stage's fused forward only, 295 ms.

        With ``columns`` the components are stacked along the first axis, ``(4, n)``, each a
        contiguous row, and the torque's ``(3, n)`` is split by rows: the rows ``(n, 4)`` made the
        law's reads and writes strided. ``simulate``'s scan path, the same PD law (one core, least
        of 9, rows -> columns): float32 forward 18.0 -> 12.8 ms, gradient 75.8 -> 67.8 ms, one
        ``jvp`` 36.4 -> 26.5 ms; float64 32.5 -> 28.0, 177 -> 164 and 61.1 -> 53.1 ms. Without
        the loops around the torque the columns cost more, as the rows did (float32 forward 34 ms
        with its value's loop alone, 98 ms with the stage's alone)."""
        if self.torque is None:
            return self.acceleration(w, None)
        q_loop, w_loop = _paired(_fusion.one_loop_both_ways, q, w)
        dtype = jnp.result_type(w[0])  # the torque in the state's dtype, as diffrax's terms
        if self.columns:  # components stacked along the first axis, the torque's split by rows
            tau = jnp.asarray(self.torque(t, jnp.stack(q_loop), jnp.stack(w_loop), args), dtype)
            parts = tuple(tau[i] for i in range(tau.shape[0]))
        else:
            parts = split(jnp.asarray(self.torque(t, stack(q_loop), stack(w_loop), args), dtype))
        return self.acceleration(w, _fusion.one_loop_both_ways(parts))


def columns_by_products(x: Array) -> Comps:
    """The components of ``x`` ``(n, k)`` as :func:`split`, each by a product with a column of the
    identity (``x e_i``: exact for finite ``x``), with the cotangent gathered back through a
    matrix product (:func:`_gather_by_product`). Used by the Lie solvers' component layout
    (``jaxquat.integration.lie_solvers``) for a rate read from ``qdot``; ``simulate``'s scan path
    used it for the torque's components until session 43 (now :mod:`jaxquat._fusion`'s loops).

    Not :func:`split`: under XLA's CPU fusion emitters (jaxlib 0.10.2, its default) the backward
    step fused the torque's cotangent, gathered by element-wise ops (the pads that transpose the
    slices, or the broadcast products that transpose these products), with the whole
    rematerialised RKMK4 step into one kernel whose subgraphs are re-evaluated once per use: in
    the generated code the calls of one subgraph multiply with the stages. Training an MLP
    torque through ``simulate``'s scan path seemed to hang (0.65 s per step for 16 bodies); the
    products in the forward pass fixed that case (0.3 ms) but not element-wise laws: the
    gradient of 1000 bodies x 100 steps took 32-40 s for five of eight laws tried, 21-50 ms
    now (``docs/integrators.md``). ``tests/test_integrators.py`` checks an MLP and a PD law
    under XLA's defaults."""
    x = _gather_by_product(x)
    eye = jnp.eye(x.shape[-1], dtype=x.dtype)
    return tuple(_arrays.matmul(x, eye[:, i]) for i in range(x.shape[-1]))


@jax.custom_jvp
def _gather_by_product(x: Array) -> Array:
    """The identity on ``x`` ``(n, k)``, whose tangent is ``dx @ I_k``, so that reverse mode
    transposes it to ``ct @ I_k``: a product with a contraction, which XLA neither fuses nor
    rewrites as element-wise, so every kernel of the backward step ends at the torque's
    cotangent (a ``custom_jvp``, not a ``custom_vjp``, so forward mode works too). Tried and not
    enough, ``jit(grad)`` of 16 bodies x 2 steps of ``-k_p sign(q_w) q_v - k_d w``: the product
    in front of :func:`split` instead of the column products (1.4 s), a stack of the
    cotangent's columns before the product (1.37 s: the stack fused instead),
    ``lax.optimization_barrier`` in the backward pass (XLA's CPU pipeline drops it before
    fusion: 0.92 s); the product in the forward pass as well worked but cost the forward pass
    (198 against 88 ms for 1000 bodies x 1000 steps, one run)."""
    return x


@_gather_by_product.defjvp
def _gather_jvp(primals: tuple[Array], tangents: tuple[Array]) -> tuple[Array, Array]:
    (x,), (dx,) = primals, tangents
    return x, _arrays.matmul(dx, jnp.eye(dx.shape[-1], dtype=dx.dtype))


class Tableau:
    """An explicit Runge-Kutta tableau as Python floats: ``a`` (lower rows), ``b``, ``c``, and
    the order of the method (the ``dexp^-1`` truncation)."""

    def __init__(self, a: Sequence[Sequence[float]], b: Sequence[float], c: Sequence[float], order: int):
        self.a = tuple(tuple(float(x) for x in row) for row in a)
        self.b = tuple(float(x) for x in b)
        self.c = tuple(float(x) for x in c)
        self.order = order

    @classmethod
    def of(cls, tableau, order: int) -> Tableau:
        """From a ``diffrax.ButcherTableau``."""
        return cls(
            [np.asarray(r).tolist() for r in tableau.a_lower],
            np.asarray(tableau.b_sol).tolist(),
            [0.0, *np.asarray(tableau.c).tolist()],
            order,
        )


LIE_EULER = Tableau([], [1.0], [0.0], 1)


def rkmk_step(
    tab: Tableau,
    field: Callable,
    t0,
    h,
    q: Comps,
    z: Comps,
    args,
    field_reads_q: bool = True,
    one_loop: bool = False,
    params: Comps = (),
    recompute: bool = False,
) -> tuple[Comps, Comps]:
    """One RKMK step of ``tab`` from ``(q, z)`` at ``t0`` over ``h``, for the Lie-algebra field
    ``field(t, q, z, args, params) -> (w_b, z')`` (the body rate on the quaternion, the derivative
    of the other components ``z``; ``params``: arrays the field reads, handed back after the
    step's input barrier, e.g. :meth:`EulerEquations.entries`): the stages ``theta_i = h sum_j a_ij k_j``,
    ``z_i = z + h sum_j a_ij l_j``, ``(w_i, l_i) = field(t0 + c_i h, q Exp(theta_i), z_i)``,
    ``k_i = dexp^-1_(theta_i)(w_i)``; then ``q Exp(h sum b_i k_i)`` (one Newton step on ``|q|``)
    and ``z + h sum b_i l_i``. ``field_reads_q=False``: ``field`` ignores its ``q``, so the stage
    attitudes ``q Exp(theta_i)`` are not formed (it is handed ``q``).

    ``one_loop``: the step compiled on CPU as one XLA loop per stage (:mod:`jaxquat._fusion`):
    each stage's slopes ``(k_i, l_i)`` and the step's result in one loop, values and forward-mode
    tangents, and the cotangents of ``(q, z)`` in one loop in reverse mode. Without it XLA
    compiles a kernel per output component, each evaluating most of the step again (3260 HLO
    operations in the seven kernels of the torque-free RKMK4 step). Measured (torque-free,
    1000 bodies x 1000 RKMK4 steps, one core of this 2-core EPYC, median of 7, float32 /
    float64): forward 26.8 / 53.9 ms -> 5.9 / 11.9 ms, gradient 70.8 / 162 ms -> 25.1 / 69.3 ms,
    one ``jvp`` 69.3 / 149 ms -> 15.5 / 30.5 ms. Tried: without the loops per stage (the whole
    step in one loop, forward 6.6 ms, gradient 28.7 ms, ``jvp`` 19.6 ms, float32); the stages'
    cotangents in one loop each as well (gradient 39.3 / 97.8 ms).

    ``recompute``: the values a stage's loop shares with the loop of the cotangents are computed
    in both (:func:`_recomputed`; the field marks its own, as
    :meth:`EulerEquations.with_entries` does with ``recompute``)."""
    dt = h  # the stage times' step: a scalar, where _inputs broadcasts h to the batch
    if one_loop:
        q, z, h, params, _ = _inputs(q, z, h, params)
    ks, ls, _ = rkmk_stages(
        tab, field, t0, dt, h, q, z, args, field_reads_q, one_loop, params=params, recompute=recompute
    )
    q1, z1, _, _ = rkmk_combine(tab.b, h, q, z, ks, ls, one_loop)
    return _paired(_fusion.one_loop, q1, z1) if one_loop else (q1, z1)


def _inputs(q: Comps, z: Comps, h, params: Comps, first: tuple[Comps, Comps] | None = None):
    """A step's inputs through reverse-mode barriers (:func:`jaxquat._fusion.one_loop_backward`),
    so that their cotangents come out of loops over the batch: ``(q, z)``, the step ``h`` and a
    carried first stage through one, the field's ``params`` (each broadcast to the batch: their
    gradients are per body there and summed over the batch after it) through another
    (:class:`EulerEquations` has why). Any input left out would be
    a reduction of its own over the whole backward step, compiled by XLA's CPU fusion emitters
    into code that re-evaluates the step's subgraphs once per use (the gradient of 10 bodies x
    1000 steps in seconds, not milliseconds: :class:`EulerEquations`)."""
    shape = jnp.shape(q[0])
    h = jnp.broadcast_to(jnp.asarray(h, jnp.result_type(q[0])), shape)
    params = tuple(jnp.broadcast_to(p, shape) for p in params)
    groups = [tuple(q), tuple(z), (h,), params]
    if first is not None:
        groups += [tuple(first[0]), tuple(first[1])]
    # the field's parameters in a loop of their own (EulerEquations: fused with the state's, their
    # cotangents were kernels of their own)
    out = _grouped(_fusion.one_loop_backward, groups[:3] + groups[4:])
    out = out[:3] + [tuple(_fusion.one_loop_backward(params)) if params else ()] + out[3:]
    return out[0], out[1], out[2][0], out[3], None if first is None else (out[4], out[5])


def _branches(one_loop: bool, stage: bool) -> str:
    """How ``exp`` chooses its branch in a step. Off the CPU, or without ``one_loop``: the
    derivatives by the whole batch. In a one-loop step on CPU, where each ``lax.cond`` cuts a
    loop in two: a stage attitude's exponential by the whole batch, value and derivatives (three
    of RKMK4's four; measured at :func:`jaxquat._safe.sinc_cos_of_sq_small_batch`), the step's
    last one (whose cut falls between the combination of the stages and the product with ``q``)
    by the batch for its derivatives only. Until session 51 a one-loop step selected every
    exponential per element: a cond on the last one had cost more when the step's loops were
    first written (the gradient of 1000 bodies x 1000 RKMK4 steps, float32, one core: 33.4 ms with
    the ``cond``, 28.9 ms without). With today's loops, torque-free, the cond on its derivatives
    gives float32 gradient 24.1 -> 24.3 ms and one ``jvp`` 12.8 -> 12.4 ms, float64 56.6 -> 52.1
    and 24.5 -> 22.3 ms, the forward pass unchanged (least of 7, one core)."""
    if not (one_loop and _trig.is_cpu()):
        return "derivatives by batch"
    return "by batch" if stage else "derivatives by batch"


def rkmk_stages(
    tab: Tableau,
    field: Callable,
    t0,
    dt,
    h,
    q: Comps,
    z: Comps,
    args,
    field_reads_q: bool = True,
    one_loop: bool = False,
    first: tuple[Comps, Comps] | None = None,
    params: Comps = (),
    recompute: bool = False,
) -> tuple[list[Comps], list[Comps], Comps]:
    """The stages of :func:`rkmk_step`: the slopes ``k_i`` (on the quaternion's local coordinates)
    and ``l_i`` (on ``z``) of every stage, and the last stage's body rate ``w_s`` (whose ``dexp^-1``
    is ``k_s``). The stage times are ``t0 + c_i dt`` and the increments scale by ``h`` (the two
    differ where diffrax flips the time axis). ``first``: the first stage's ``(w_1, l_1)`` when it
    is known already (a first-same-as-last tableau's last stage of the step before). With
    ``one_loop`` each stage's slopes but the last pass through one loop (the last stage goes into
    the loop of whatever combines them). ``recompute``: the stage increments ``theta_i`` and
    ``z_i`` and ``dexp^-1``'s cross products through :func:`_recomputed` (the field's own values
    are the field's to mark)."""
    ks: list[Comps] = []
    ls: list[Comps] = []
    wi: Comps = ()
    for i in range(len(tab.b)):
        if i == 0:
            theta, qi, zi = None, q, z
        else:
            row = tab.a[i - 1]
            theta = _recomputed(_weighted(list(zip(row, ks)), h), recompute)
            zi = _recomputed(_add(z, _weighted(list(zip(row, ls)), h)), recompute)
            # a field that does not read q (torque-free Euler's equations) is not handed the stage
            # attitudes: XLA dropped them, but every trace of the step built them (tracing the
            # first simulate at batch 1000: 0.075 -> 0.055 s; one Adam step through it 0.30 ->
            # 0.24-0.26 s; the same values and gradients to the bit)
            qi = multiply(q, exp(theta, _branches(one_loop, stage=True))) if field_reads_q else q
        if i == 0 and first is not None:
            wi, li = first
        else:
            wi, li = field(t0 + tab.c[i] * dt, qi, zi, args, params)
        ki = wi if theta is None else dexpinv(theta, wi, tab.order, recompute)
        if one_loop and i < len(tab.b) - 1:
            ki, li = _paired(_fusion.one_loop, ki, li)
        ks.append(ki)
        ls.append(li)
    return ks, ls, wi


def rkmk_combine(
    weights: Sequence[float], h, q: Comps, z: Comps, ks: list[Comps], ls: list[Comps], one_loop: bool = False
) -> tuple[Comps, Comps, Comps, Comps]:
    """``(q Exp(theta), z + dz, theta, dz)`` with ``theta = h sum_i b_i k_i`` and
    ``dz = h sum_i b_i l_i`` for the weights ``b_i`` (one Newton step on ``|q|``)."""
    theta = _weighted(list(zip(weights, ks)), h)
    dz = _weighted(list(zip(weights, ls)), h)
    return unit(multiply(q, exp(theta, _branches(one_loop, stage=False)))), _add(z, dz), theta, dz


class LieStep(NamedTuple):
    """The parts of one step of a Lie solver on the rigid body, in components (:func:`lie_step`):
    the state at the step's end, the increments ``theta = h sum b_i k_i`` and ``dz``, the error
    estimate (``q1 (0, e/2)`` and ``e_z``; None without error weights), the dense output's end
    slopes ``h (k_1, l_1)`` and ``h (dexp^-1_theta(w_s), l_s)``, its midpoint increments (None
    without midpoint weights), and the last stage's ``(w_s, l_s)`` (the next step's first stage
    for a first-same-as-last tableau). Without ``dense``, the increments and slopes are None;
    without ``carry``, the last stage."""

    q1: Comps
    z1: Comps
    theta: Comps | None
    dz: Comps | None
    error: tuple[Comps, Comps] | None
    start: tuple[Comps, Comps] | None
    end: tuple[Comps, Comps] | None
    mid: tuple[Comps, Comps] | None
    last: tuple[Comps, Comps] | None


def lie_step(
    tab: Tableau,
    field: Callable,
    t0,
    dt,
    h,
    q: Comps,
    z: Comps,
    args,
    field_reads_q: bool = True,
    b_error: Sequence[float] | None = None,
    mid_weights: Sequence[float] | None = None,
    first: tuple[Comps, Comps] | None = None,
    params: Comps = (),
    dense: bool = True,
    carry: bool = True,
) -> LieStep:
    """One RKMK step of ``tab`` as :func:`rkmk_step` computes it (each stage one loop on CPU, the
    cotangents of ``(q, z)`` one loop), with everything a diffrax solver returns besides the state
    (:class:`LieStep`) computed in the result's loop: what the Lie solvers of
    :mod:`jaxquat.integration.lie_solvers` run on a rigid-body model (``euler_equations``).
    ``dense=False`` (no dense output: ``RKMK4``, ``LieEuler``, a solver saving at step ends) leaves
    out the increments and the slopes, ``carry=False`` (no first-same-as-last stage) the last
    stage. Writing them all (the 31 arrays of ``RKMK4``'s last loop instead of 7), ``diffeqsolve``
    of 1000 bodies took 52 ms against 7.3 ms once the step was a jitted function of its own
    (``lie_solvers``): XLA kept the unused outputs."""
    q, z, h, params, first = _inputs(q, z, h, params, first)
    ks, ls, w_last = rkmk_stages(tab, field, t0, dt, h, q, z, args, field_reads_q, True, first, params)
    q1, z1, theta, dz = rkmk_combine(tab.b, h, q, z, ks, ls, True)
    pairs: dict[str, tuple[Comps, Comps]] = {"state": (q1, z1)}
    if dense:
        pairs["incr"] = (theta, dz)
    if b_error is not None:
        e, e_z = _weighted(list(zip(b_error, ks)), h), _weighted(list(zip(b_error, ls)), h)
        q_error = _quaternion.multiply_components(q1, (None, *(0.5 * x for x in e)))  # no None: q1 has none
        pairs["error"] = (cast(Comps, tuple(q_error)), e_z)
    if dense:
        pairs["start"] = (tuple(h * x for x in ks[0]), tuple(h * x for x in ls[0]))
        pairs["end"] = (tuple(h * x for x in dexpinv(theta, w_last, tab.order)), tuple(h * x for x in ls[-1]))
        if mid_weights is not None:
            pairs["mid"] = (_weighted(list(zip(mid_weights, ks)), h), _weighted(list(zip(mid_weights, ls)), h))
    if carry:
        pairs["last"] = (w_last, ls[-1])
    looped = iter(_grouped(_fusion.one_loop, [g for pair in pairs.values() for g in pair]))
    got = {name: (next(looped), next(looped)) for name in pairs}
    incr = got.get("incr", (None, None))
    return LieStep(
        *got["state"], *incr, got.get("error"), got.get("start"), got.get("end"), got.get("mid"), got.get("last")
    )


def solve(tab: Tableau, euler: EulerEquations, ts: Array, q0: Array, w0: Array, args: Any, substeps: int):
    """``(q, w_b)`` of the rigid body at every ``ts`` (leading axis ``len(ts)``), ``substeps``
    equal RKMK steps of ``tab`` per interval, on the Lie-algebra field ``(w_b, euler(t, q, w_b,
    args))``, driven by :func:`jaxquat.integration.fixed_step.scan_steps` (each step
    rematerialised in reverse mode), each step compiled as a few loops (``one_loop``)."""

    def field(t, q, w, step_args, entries):
        return w, euler.with_entries(entries, recompute=True)(t, q, w, step_args)

    def step(y, t0, t1, step_args, jump):
        del jump  # no solver state to refresh
        return rkmk_step(
            tab, field, t0, t1 - t0, y[0], y[1], step_args, euler.torque is not None, True, euler.entries(), True
        )

    qs, ws = scan_steps(step, ts, (split(q0), split(w0)), args, substeps=substeps)
    return stack(qs), stack(ws)
