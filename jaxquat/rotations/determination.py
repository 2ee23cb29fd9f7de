"""Static attitude determination from vector observations: TRIAD, QUEST, Davenport's q-method
(``align_vectors``), Shuster's covariance.

Convention (the library's): the attitude ``q`` rotates body vectors into the reference
frame, ``r = R(q) b``; a measured body vector is ``b = R(q)^T r + noise``. Errors are
body-frame rotation vectors: ``q_true = q Exp(dtheta)`` (:func:`jaxquat.plus`), so a
covariance here is the covariance of ``dtheta`` in radians squared.

Wahba's problem with weights ``w_i``: minimise ``sum_i w_i |r_i - R(q) b_i|^2``.
:func:`align_vectors` solves it by a 4x4 eigendecomposition (Davenport's q-method: ``eigh``,
or on CPU for a batch of 1024 problems or more Jacobi rotations over the batch);
:func:`quest` finds the same top eigenpair of Davenport's ``K`` by Newton's method on its
characteristic polynomial (Shuster & Oh 1981), with no eigen-decomposition.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _fusion, _quaternion, _rates, _rotation, _safe

__all__ = ["triad", "quest", "align_vectors", "attitude_covariance"]

_NEWTON_STEPS = 6


def _unit(v: Array) -> Array:
    return v / jnp.sqrt(_safe.norm_sq(v))[..., None]


def triad(
    b1: Float[ArrayLike, "*#batch 3"],
    b2: Float[ArrayLike, "*#batch 3"],
    r1: Float[ArrayLike, "*#batch 3"],
    r2: Float[ArrayLike, "*#batch 3"],
) -> Float[Array, "*batch 4"]:
    """TRIAD (Black 1964; Shuster & Oh 1981): the attitude from two vector pairs.

    Body vectors ``b1, b2`` and the same directions ``r1, r2`` in the reference frame. The
    orthonormal triads ``T_b = (t1, t2, t3)`` of ``(b1, b2)`` and ``T_r`` of ``(r1, r2)``
    (``t1 = v1/|v1|``, ``t2 = v1 x v2/|v1 x v2|``, ``t3 = t1 x t2``) give
    ``R(q) = T_r T_b^T``, so ``R(q) b1 || r1`` exactly and ``b2`` only fixes the rotation
    about ``b1``: put the more accurate sensor first. Canonical sign (``w >= 0``).
    Vectors need not be unit. Parallel ``b1, b2`` (or ``r1, r2``) carry no attitude
    information about that axis: the result is NaN.
    """
    names = ["b1", "b2", "r1", "r2"]
    vs = [_checks.vec3(v, n) for v, n in zip((b1, b2, r1, r2), names)]
    return _arrays.compiled_rows(_triad, (1, 1, 1, 1), *_checks.broadcast_batch(vs, names, [1, 1, 1, 1]))


def _triad(b1: Array, b2: Array, r1: Array, r2: Array) -> Array:
    # The triads and R on components, R's nine entries in one loop both ways. As rows (the triads
    # stacked, R by an einsum: a batched 3x3 product) until session 53: 10^5 problems, one core,
    # least of 7, value and the gradient of sum(q * W) in r1, float32 4.0 / 10.5 -> 2.2 / 5.1 ms,
    # float64 12.3 / 18.0 -> 4.0 / 12.4 ms.
    tr, tb = _frame_parts(r1, r2), _frame_parts(b1, b2)
    # R = T_r T_b^T entry by entry: R_ij = sum_k (t_k)_i (t'_k)_j
    m = [tr[0][i] * tb[0][j] + tr[1][i] * tb[1][j] + tr[2][i] * tb[2][j] for i in range(3) for j in range(3)]
    m = _fusion.one_loop_both_ways(jnp.broadcast_arrays(*m))
    return _rotation.from_matrix_shepperd(jnp.stack(m, axis=-1).reshape(m[0].shape + (3, 3)))


def _frame_parts(v1: Array, v2: Array) -> list[list[Array]]:
    """The triad of ``(v1, v2)``, its columns ``t1 = v1/|v1|``, ``t2 = (v1 x v2)/|v1 x v2|``,
    ``t3 = t1 x t2``, on components (three lists of three arrays)."""
    a, b = _arrays.components(v1), _arrays.components(v2)
    c = _rates.cross_parts(a, b)
    t1 = _scaled(a, 1.0 / jnp.sqrt(_rates.dot_parts(a, a)))
    t2 = _scaled(c, 1.0 / jnp.sqrt(_rates.dot_parts(c, c)))
    return [t1, t2, _rates.cross_parts(t1, t2)]


def _scaled(v: list[Array], s: Array) -> list[Array]:
    return [s * x for x in v]


def _adjugate(m: Array) -> list[list[Array]]:
    """``adj(m)`` of a 4x4 ``m`` as nested lists of entries: 3x3 cofactors written out (no LU)."""
    e = [[m[..., i, j] for j in range(4)] for i in range(4)]

    def minor(i, j):
        rows = [r for r in range(4) if r != i]
        cols = [c for c in range(4) if c != j]
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = ([e[r][c_] for c_ in cols] for r in rows)
        return a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)

    return [[(-1.0) ** (i + j) * minor(j, i) for j in range(4)] for i in range(4)]


def _best_column(adj: list[list[Array]]) -> Array:
    """The column of the adjugate with the largest diagonal entry, normalised, canonical sign.

    For ``m = K - lambda I`` at a simple eigenvalue ``lambda``, ``adj(m) = c v v^T`` with ``v``
    the eigenvector and ``c`` the product of the other eigenvalue gaps, so every column is
    proportional to ``v`` and the largest-diagonal one is the best conditioned.
    """
    best = jnp.argmax(jnp.stack([jnp.abs(adj[i][i]) for i in range(4)], axis=-1), axis=-1)
    cols = jnp.stack([jnp.stack([adj[r][c] for r in range(4)], axis=-1) for c in range(4)], axis=-2)
    col = jnp.take_along_axis(cols, best[..., None, None], axis=-2)[..., 0, :]
    return _quaternion.canonicalize(_unit(col))


def _shifted(k: Array, lam: Array) -> Array:
    """``K - lam I`` for stacks of 4x4 ``K``."""
    return k - lam[..., None, None] * jnp.broadcast_to(jnp.eye(4, dtype=k.dtype), k.shape)


def _quest_newton(k: Array, lam0: Array) -> Array:
    """The largest root of ``det(K - lambda I) = lambda^4 - (tr K^2 / 2) lambda^2 - (tr K^3 / 3) lambda
    + det K`` (``K`` is traceless) by Newton's method from ``lam0 >= lambda_max``, where the quartic
    is increasing and convex, so the iterates decrease monotonically to the root.

    The coefficients are written out entry by entry (``K^2`` by products, ``det K`` by its first
    row's cofactors): as an ``einsum`` and ``det`` XLA on CPU ran a batched 4x4 matrix product and
    an LU factorisation per matrix, 17 and 13 ms of ``quest``'s 94 ms for 10^5 problems in float64
    (the profiler's figures); ``quest`` took 95-99 ms before and 36 ms after (one core, least of
    7). Float32 skips Newton (see :func:`_quest_eigenpair`)."""
    e = [[k[..., i, j] for j in range(4)] for i in range(4)]
    k2 = [
        [e[i][0] * e[0][j] + e[i][1] * e[1][j] + e[i][2] * e[2][j] + e[i][3] * e[3][j] for j in range(4)]
        for i in range(4)
    ]
    a = 0.5 * (k2[0][0] + k2[1][1] + k2[2][2] + k2[3][3])
    b = sum(k2[i][j] * e[j][i] for i in range(4) for j in range(4)) / 3.0
    adj = _adjugate(k)
    c = e[0][0] * adj[0][0] + e[0][1] * adj[1][0] + e[0][2] * adj[2][0] + e[0][3] * adj[3][0]

    def step(_, lam):
        p = ((lam * lam - a) * lam - b) * lam + c
        dp = (4.0 * lam * lam - 2.0 * a) * lam - b
        return lam - p / jnp.where(dp == 0, 1.0, dp)

    return jax.lax.fori_loop(0, _NEWTON_STEPS, step, lam0)


def _quest_eigenpair(k: Array, lam0: Array) -> tuple[Array, Array]:
    """``lambda_max`` by Newton on the characteristic quartic, then Rayleigh-quotient refinement.

    The quartic's coefficients are O(|K|^4) and cancel near the root, so Newton's root is only
    good to ``eps |K|^4 / p'``, and ``p'`` is the product of the eigenvalue gaps: when two
    eigenvalues are close (nearly parallel vectors) the adjugate column at that root leans
    toward the other eigenvector. Each Rayleigh quotient ``v^T K v`` of the column is accurate
    to ``eps |K|`` plus the square of the column's error (inverse iteration with a Rayleigh
    shift). Measured against scipy on three vectors ``d`` apart (eigenvalue gap ``d^2``, noise
    1e-5): float64, ``d = 1e-3``: 1.4e-5 rad with Newton alone, 8e-11 after one quotient (eigh:
    9e-11); float32, ``d = 3e-2``: 0.12 rad after one quotient, 6e-3 after two, 4e-5 after three
    (eigh: 2e-5). So one quotient in float64 and three in lower precision.

    In lower precision the refinement starts from the upper bound ``lam0`` instead of Newton's
    root. With a gap of ``d^2`` the quartic's rounding can move its two top roots together (or
    off the real line): on one machine (XLA's default CPU flags, float32, ``d = 3e-2``) Newton
    stopped at 3.00048 between ``lambda_2`` = 2.99940 and ``lambda_max`` = 3.00180, nearer
    ``lambda_2``, and the quotients converged to ``lambda_2``'s eigenvector: 3.13 rad off. The
    column at ``lam0 >= lambda_max`` is a step of inverse iteration shifted above
    ``lambda_max``, which favours its eigenvector by ``(lambda_max - lambda_2)/(lam0 -
    lambda_max)`` (exact for noise-free data, where ``lam0 = lambda_max``); the same problem
    then gives 4.9e-5 rad on both machines' flag settings.

    The quotient is written out on the entries (:func:`jaxquat._arrays.matvec`): as an ``einsum``
    XLA on CPU ran a batched 4x4 product per quotient. ``quest`` of 2 x 10^4 problems of 10 pairs
    (one core, least of 15, two processes each): float32 4.0-4.2 -> 2.0-2.1 ms, gradient 6.0-6.4
    -> 4.2-4.3 ms; float64 2.7-3.1 -> 2.2-2.5 ms, gradient 5.9-6.1 -> 5.5-5.9 ms. The same
    written out in the derivative (``dK v`` in :func:`_quest_kernel_jvp`, and the top
    eigenvector's ``jvp``) made the gradients slower (``quest`` float32 4.3 -> 4.8 ms,
    ``align_vectors`` 6.2 -> 7.5 ms): XLA fused the products into each use.
    """
    float64 = k.dtype == jnp.float64
    lam = _quest_newton(k, lam0) if float64 else lam0
    for _ in range(1 if float64 else 3):
        v = _best_column(_adjugate(_shifted(k, lam)))
        lam = _arrays.dot(v, _arrays.matvec(k, v))
    return lam, _best_column(_adjugate(_shifted(k, lam)))


@jax.custom_jvp
def _quest_kernel(k: Array, lam0: Array) -> Array:
    return _quest_eigenpair(k, lam0)[1]


@_quest_kernel.defjvp
def _quest_kernel_jvp(primals, tangents):
    # Differentiating (K - lam) v = 0 with v^T v = 1: dlam = v^T dK v and
    # (K - lam I + v v^T) dv = -(I - v v^T) dK v, a 4x4 solve (the matrix is regular when
    # lam is simple: it has eigenvalue 1 on v and the gaps lam_j - lam elsewhere).
    (k, lam0), (dk, _) = primals, tangents
    lam, v = _quest_eigenpair(k, lam0)
    dkv = _arrays.einsum("...ij,...j->...i", dk, v)
    rhs = -(dkv - v * jnp.sum(v * dkv, axis=-1, keepdims=True))
    n = _shifted(k, lam) + v[..., :, None] * v[..., None, :]
    return v, _solve(n, rhs)


def _solve(m: Array, b: Array) -> Array:
    """``m x = b`` for stacks of small square ``m`` ``(..., k, k)`` and ``b`` ``(..., k)``: Gaussian
    elimination with partial pivoting (each column's pivot the entry of largest size at or below
    the diagonal), written out on the entries. ``jnp.linalg.solve`` ran an LU factorisation, a
    sort of its pivots and two triangular solves per 4x4 matrix on CPU: 36 ms of the 89 ms
    gradient of ``quest`` for 10^5 problems in float32 (the profiler's figures)."""
    k = m.shape[-1]
    rows = [[m[..., i, j] for j in range(k)] + [b[..., i]] for i in range(k)]
    for c in range(k):
        for r in range(c + 1, k):  # the larger of the two into the pivot row
            swap = jnp.abs(rows[r][c]) > jnp.abs(rows[c][c])
            rows[c], rows[r] = (
                [jnp.where(swap, y, x) for x, y in zip(rows[c], rows[r])],
                [jnp.where(swap, x, y) for x, y in zip(rows[c], rows[r])],
            )
        for r in range(c + 1, k):
            f = rows[r][c] / rows[c][c]
            rows[r] = rows[r][: c + 1] + [rows[r][j] - f * rows[c][j] for j in range(c + 1, k + 1)]
    x: list[Array] = [jnp.zeros_like(b[..., 0])] * k
    for i in reversed(range(k)):
        total = rows[i][k]
        for j in range(i + 1, k):
            total = total - rows[i][j] * x[j]
        x[i] = total / rows[i][i]
    return jnp.stack(x, axis=-1)


def _observations(vectors_body, vectors_ref, weights):
    b, r, w = _checks.vector_pairs(vectors_body, vectors_ref, weights, ("vectors_body", "vectors_ref"))
    if b.shape[-2] < 2:
        raise ValueError(
            "argument 'vectors_body' must hold n >= 2 vectors (..., n, 3) to fix an attitude, got shape "
            f"{tuple(b.shape)}"
        )
    return b, r, jnp.ones(b.shape[:-1], b.dtype) if w is None else w


def quest(
    vectors_body: Float[ArrayLike, "*#batch n 3"],
    vectors_ref: Float[ArrayLike, "*#batch n 3"],
    weights: Float[ArrayLike, "*#batch n"] | None = None,
) -> Float[Array, "*batch 4"]:
    """QUEST (Shuster & Oh 1981): the attitude ``q`` minimising ``sum_i w_i |r_i - R(q) b_i|^2``.

    The optimal ``q`` is the eigenvector of Davenport's ``K(B)``, ``B = sum_i w_i r_i b_i^T``,
    for its largest eigenvalue ``lambda_max`` (the same problem and answer as
    ``align_vectors(vectors_ref, vectors_body, weights)``). QUEST finds ``lambda_max`` by
    Newton's method on the characteristic quartic from ``lambda_0 = sum_i w_i |r_i| |b_i|``
    (an upper bound, exact for noise-free data; 6 steps) and the eigenvector as a column of
    the adjugate ``adj(K - lambda_max I)``, whose columns are all proportional to it, refined
    by Rayleigh quotients (once in float64; three times in float32, starting from
    ``lambda_0`` itself: rounding can put the quartic's root nearer the second eigenvalue). Taking
    the column with the largest diagonal entry replaces Shuster's method of sequential
    rotations: it has no singularity at 180 degrees. Canonical sign (``w >= 0``).

    Differentiated by a custom JVP (``dlambda = q^T dK q`` and a 4x4 solve for ``dq``), exact
    wherever ``lambda_max`` is simple: at least two non-parallel vectors with positive weight.

    Bad input: fewer than two vector pairs, or mismatched shapes, raise ``ValueError`` at trace
    time; weights are checked as in :func:`jaxquat.mean`. Parallel vectors give NaN or an
    arbitrary rotation about their common axis.
    """
    b, r, w = _observations(vectors_body, vectors_ref, weights)
    return _arrays.compiled(_quest, b, r, w)


def _quest(b: Array, r: Array, w: Array) -> Array:
    """:func:`quest` after its argument checks, compiled as one program (an eager call ran the
    Newton loop and the refinement op by op: 1.58 s first and 77 ms for every later call of the
    contract suite's 12 problems; now 0.68 s and 0.5 ms)."""
    dtype = b.dtype
    work = _checks.working_dtype(dtype)
    b, r, w = b.astype(work), r.astype(work), w.astype(work)
    bmat = _arrays.outer_sum(r, b, w)
    lam0 = _arrays.sum_last(w * jnp.sqrt(_safe.norm_sq(r) * _safe.norm_sq(b)))
    return _quest_kernel(_rotation.k_matrix(bmat), lam0).astype(dtype)


def attitude_covariance(
    vectors_body: Float[ArrayLike, "*#batch n 3"], noise: Float[ArrayLike, "*#batch n"] | float
) -> Float[Array, "*batch 3 3"]:
    """Shuster's QUEST measurement-model covariance of the attitude error (body frame, rad^2).

    Each unit body vector ``b_i`` is measured with an isotropic angular error of standard
    deviation ``noise_i`` (radians) in the plane normal to it; the optimal (QUEST / q-method)
    estimate with weights ``1/noise_i^2`` then has error covariance
    ``P = (sum_i noise_i^-2 (I - b_i b_i^T))^-1`` for ``q_true = q Exp(dtheta)`` (Shuster & Oh
    1981; Markley & Crassidis 2014, section 5.5). The ``b_i`` are normalised here.
    With all vectors parallel ``P`` does not exist (infinite about that axis): the result is
    then inf/NaN.
    """
    b = _checks.vec3(vectors_body, "vectors_body")
    if b.ndim < 2:
        raise ValueError(f"argument 'vectors_body' must be shaped (..., n, 3), got shape {tuple(b.shape)}")
    s = _checks.scalar_like(noise, "noise")
    s = jnp.broadcast_to(s, s.shape if s.ndim else b.shape[-2:-1])
    s = _checks.per_item(s, "noise", b, "vectors_body")
    b, s = _checks.arguments(vectors_body=(b, "vectors"), noise=(s, "scalars"))
    return _arrays.compiled(_attitude_covariance, b, s)


def _attitude_covariance(b: Array, s: Array) -> Array:
    """``F^-1`` with ``F = sum_n w_n (I - u_n u_n^T) = (sum_n w_n) I - S``, ``w_n = 1/s_n^2`` and
    ``S = sum_n w_n u_n u_n^T`` (:func:`jaxquat._arrays.outer_sum`'s one-loop sums), inverted by
    its cofactors (:func:`jaxquat._arrays.symmetric_inverse_parts`). As an ``einsum`` over a
    ``(..., n, 3, 3)`` stack and ``jnp.linalg.inv`` (an LU per matrix), until session 52: 10^5
    problems of 5 vectors (one core, least of 7; the gradient of ``sum(P * W)`` in the vectors):
    float32 24 -> 1.0 ms, gradient 90 -> 16 ms; float64 40 -> 2.0 ms, 119 -> 45 ms. Session 53:
    the unit vectors' norms taken from the components (``outer_sum_entries(..., unit=True)``)
    and the nine entries' cotangents in one loop (:func:`jaxquat._fusion.one_loop_backward`):
    the gradient, measured against session 52's code on one day, 22 -> 8.1 ms (float32) and
    52 -> 24 ms (float64)."""
    dtype, work = b.dtype, _checks.working_dtype(b.dtype)
    b, s = b.astype(work), s.astype(work)
    w = 1.0 / (s * s)
    # u_n u_n^T = b_n b_n^T / |b_n|^2: the normalisation folded into the weights of the sums
    outer = _arrays.outer_sum_entries(b, None, w, unit=True)
    total = _arrays.sum_last(w)
    upper = [(total if i == j else 0.0) - outer[i][j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))]
    flat = _fusion.one_loop_backward(
        jnp.broadcast_arrays(*[x for r in _arrays.symmetric_inverse_parts(upper) for x in r])
    )
    return jnp.stack([jnp.stack(flat[3 * i : 3 * i + 3], axis=-1) for i in range(3)], axis=-2).astype(dtype)


def align_vectors(
    a: Float[ArrayLike, "*#batch n 3"],
    b: Float[ArrayLike, "*#batch n 3"],
    weights: Float[ArrayLike, "*#batch n"] | None = None,
    *,
    return_sensitivity: bool = False,
) -> Float[Array, "*batch 4"] | tuple[Float[Array, "*batch 4"], Float[Array, "*batch 3 3"]]:
    """Rotation ``q`` minimising ``sum_i w_i |a_i - R(q) b_i|^2`` (Wahba's problem).

    Solved by Davenport's q-method: ``q`` is the top eigenvector of
    ``K = [[tr B, z^T], [z, B + B^T - tr(B) I]]`` with ``B = sum_i w_i a_i b_i^T``
    and ``z = (B21 - B12, B02 - B20, B10 - B01)``, since
    ``q^T K q = sum_i w_i a_i . R(q) b_i``. The same convention as scipy's
    ``Rotation.align_vectors(a, b)``: ``a ~ R b``. Canonical sign (``w >= 0``).

    With a single vector pair (``n == 1``, known at trace time) the problem is
    underdetermined; the minimal rotation taking ``b`` onto ``a`` is returned
    (Horn's closed form ``normalize(|a||b| + a.b, b x a)``; a rotation by pi
    about an axis perpendicular to ``b`` when they are antiparallel, to within
    ``|b x a| <= sqrt(eps) |a||b|``: ``R(q) b`` is then within about ``sqrt(eps)``
    radians of ``a``'s direction, 3.2e-4 in float32 and 1.2e-8 in float64 at most,
    measured). With
    ``n >= 2`` vectors all parallel the answer is likewise not unique and the
    gradient does not exist.

    With ``return_sensitivity=True`` the result is ``(q, S)`` with scipy's sensitivity matrix
    ``S = mean(w) (kappa I + B B^T) / zeta``, ``kappa = (lambda^2 - |B|_F^2) / 2``,
    ``zeta = lambda kappa - det B`` (``lambda = q^T K q``, the sum of ``B``'s proper singular
    values; Markley & Crassidis 2014, section 5.5). It is the covariance of the error rotation
    vector in the frame of ``a`` (``q_true = Exp(e) q``) divided by the variance of one unit-weight
    measurement: with weights ``1/s_i^2`` and unit vectors, ``S / mean(w)`` is that covariance,
    ``(sum_i w_i (I - a_i a_i^T))^-1`` to first order. Needs ``n >= 2`` (a ``ValueError`` otherwise).

    Bad input: no vectors (``n = 0``) raises ``ValueError`` at trace time; weights
    are checked as in :func:`mean`. A problem with no information (a zero vector
    when ``n == 1``; every weighted product ``a_i b_i^T`` zero, e.g. all vectors
    zero) gives NaN for that element, under ``jit`` or not.
    """
    a, b, weights = _checks.vector_pairs(a, b, weights, ("a", "b"))
    if return_sensitivity and a.shape[-2] == 1:
        raise ValueError(
            "align_vectors(..., return_sensitivity=True) needs at least two vector pairs (n >= 2 in "
            f"(..., n, 3)): a single vector pair leaves the rotation about it undetermined, got shape {tuple(a.shape)}"
        )
    if weights is None:
        return _arrays.compiled(_align_vectors, a, b, return_sensitivity=return_sensitivity)
    return _arrays.compiled(_align_vectors, a, b, weights, return_sensitivity=return_sensitivity)


def _align_vectors(a: Array, b: Array, weights: Array | None = None, *, return_sensitivity: bool):
    unweighted = weights is None
    if weights is None:
        weights = jnp.ones(a.shape[:-1], a.dtype)
        bad = jnp.zeros(a.shape[:-2], bool)
    else:
        bad = ~_arrays.valid_weights(weights)
    if a.shape[-2] == 1:
        degenerate = (_safe.norm_sq(a[..., 0, :]) == 0) | (_safe.norm_sq(b[..., 0, :]) == 0)
        return _arrays.nan_where(bad | degenerate, _rotation.minimal_rotation(a[..., 0, :], b[..., 0, :]))
    bmat = _arrays.outer_sum(a, b, None if unweighted else weights)
    k = _rotation.k_matrix(bmat)
    q = _arrays.nan_where(bad | jnp.all(bmat == 0, axis=(-2, -1)), _rotation.top_eigenvector(k))
    if not return_sensitivity:
        return q
    return q, _sensitivity(k, q, bmat, weights)


def _sensitivity(k: Array, q: Array, bmat: Array, weights: Array) -> Array:
    """scipy's ``align_vectors`` sensitivity from Davenport's eigenpair, without an SVD: with ``s_i``
    the proper singular values of ``B``, ``lambda = s_1 + s_2 + s_3``, ``kappa = sum_{i<j} s_i s_j``
    and ``zeta = prod_{i<j} (s_i + s_j)``, written through ``tr(B B^T)`` and ``det B``."""
    lam = _arrays.einsum("...i,...ij,...j->...", q, k, q)
    bbt = _arrays.einsum("...ik,...jk->...ij", bmat, bmat)
    kappa = 0.5 * (lam * lam - jnp.trace(bbt, axis1=-2, axis2=-1))
    zeta = lam * kappa - jnp.linalg.det(bmat)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=bmat.dtype), bbt.shape)
    scale = jnp.mean(weights, axis=-1) / zeta
    return scale[..., None, None] * (kappa[..., None, None] * eye + bbt)
