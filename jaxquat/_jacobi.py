"""The eigendecomposition of a batch of symmetric 4x4 matrices by cyclic Jacobi rotations, written
on components: what Davenport's ``K`` (``align_vectors``, ``from_matrix(nearest=True)``) and
``mean``'s ``sum q q^T`` are solved with on CPU for a batch of 1024 matrices or more
(:func:`jaxquat._rotation.top_eigenvector`; smaller batches call ``eigh``: the rotations' loop
compiles for about 0.3 s more).

Hand-written because LAPACK's ``eigh``, which JAX calls on CPU once per matrix, costs about a
microsecond per 4x4 matrix in call overhead: ``eigh`` of 10^5 random symmetric 4x4 matrices took
119 ms in float32 and 132-140 ms in float64, these rotations 17 ms (four sweeps) and 61 ms (six
sweeps), one core of this 2-core EPYC, least of 5. Jacobi's method is also the accurate one for
this size: each rotation is orthogonal to rounding, and the eigenvalues come out with an error
of about ``eps |K|`` (Demmel and Veselic 1992).

The rotations zero the off-diagonal entries in the cyclic order ``(0, 1), (2, 3), (0, 2), (1, 3),
(0, 3), (1, 2)``; each sweep's 26 results (10 entries of the symmetric matrix, 16 of the
eigenvector matrix) are computed in one loop over the batch (:mod:`jaxquat._fusion`). Sweeps run
until every matrix's off-diagonal part is below ``eps`` of its largest entry (quadratic
convergence: 4-6 sweeps), at most :data:`_MAX_SWEEPS`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from . import _fusion

_N = 4
_PAIRS = ((0, 1), (2, 3), (0, 2), (1, 3), (0, 3), (1, 2))
_UPPER = tuple((i, j) for i in range(_N) for j in range(i, _N))
_FULL = tuple((i, j) for i in range(_N) for j in range(_N))
# Convergence is quadratic once the off-diagonal part is below the gaps; random matrices took 4
# (float32) to 6 (float64) sweeps. The cap only bounds a matrix that never converges (NaN).
_MAX_SWEEPS = 16


def _key(i: int, j: int) -> tuple[int, int]:
    return (i, j) if i <= j else (j, i)


def _rotate(a: dict, v: dict, p: int, q: int) -> None:
    """One Jacobi rotation in the plane ``(p, q)``, zeroing ``a[p, q]``: ``t = tan(phi)`` the
    smaller root of ``t^2 + 2 t d/(2 a_pq) - 1 = 0`` with ``d = a_qq - a_pp`` (0 where
    ``a_pq = 0``), ``a' = J^T a J``, ``v' = v J``. In place on the dicts."""
    apq, app, aqq = a[_key(p, q)], a[(p, p)], a[(q, q)]
    d = aqq - app
    denom = jnp.abs(d) + jnp.sqrt(d * d + 4.0 * apq * apq)
    zero = denom == 0.0
    t = jnp.where(zero, 0.0, 2.0 * apq * jnp.where(d >= 0.0, 1.0, -1.0) / jnp.where(zero, 1.0, denom))
    c = jax.lax.rsqrt(1.0 + t * t)
    s = t * c
    for r in range(_N):
        if r in (p, q):
            continue
        arp, arq = a[_key(r, p)], a[_key(r, q)]
        a[_key(r, p)] = c * arp - s * arq
        a[_key(r, q)] = s * arp + c * arq
    a[(p, p)] = app - t * apq
    a[(q, q)] = aqq + t * apq
    a[_key(p, q)] = jnp.zeros_like(apq)
    for r in range(_N):
        vrp, vrq = v[(r, p)], v[(r, q)]
        v[(r, p)] = c * vrp - s * vrq
        v[(r, q)] = s * vrp + c * vrq


def _off(a: dict) -> Array:
    """The sum of squares of the off-diagonal entries above the diagonal."""
    terms = [a[(i, j)] * a[(i, j)] for i, j in _UPPER if i != j]
    total = terms[0]
    for term in terms[1:]:
        total = total + term
    return total


def eigh4(k: Array) -> tuple[Array, Array]:
    """Eigenvalues ``(..., 4)`` (in no particular order) and the matching unit eigenvectors as the
    columns of ``(..., 4, 4)`` of symmetric ``k`` ``(..., 4, 4)`` (its upper triangle is read).
    NaN entries give NaN. Not differentiable in reverse mode (a ``while_loop``): its caller,
    :func:`jaxquat._rotation.top_eigenvector`, differentiates through its own custom JVP. Tried
    and not kept: the sweeps run on blocks of 1024-8192 matrices, each block's loop to its own
    convergence, so that a block's 26 arrays stay in cache (``_arrays.rows_at_a_time``):
    ``align_vectors`` of 10^5 problems in float64 69 -> 105-130 ms."""
    scale = jnp.abs(k[..., 0, 0])
    for i, j in _UPPER[1:]:  # the largest entry's size, written out (a reduce over 16 is slow on CPU)
        scale = jnp.maximum(scale, jnp.abs(k[..., i, j]))
    scale = jnp.where(scale > 0.0, scale, 1.0)
    a0 = tuple(k[..., i, j] / scale for i, j in _UPPER)
    v0 = tuple(jnp.full(k.shape[:-2], 1.0 if i == j else 0.0, k.dtype) for i, j in _FULL)
    tol = jnp.finfo(k.dtype).eps ** 2

    def sweep(state):
        count, a_parts, v_parts = state
        a, v = dict(zip(_UPPER, a_parts)), dict(zip(_FULL, v_parts))
        for p, q in _PAIRS:
            _rotate(a, v, p, q)
        out = _fusion.one_loop([a[x] for x in _UPPER] + [v[x] for x in _FULL])
        return count + 1, out[: len(_UPPER)], out[len(_UPPER) :]

    def unconverged(state):
        count, a_parts, _ = state
        return (count < _MAX_SWEEPS) & jnp.any(_off(dict(zip(_UPPER, a_parts))) > tol)

    _, a_parts, v_parts = jax.lax.while_loop(unconverged, sweep, (0, a0, v0))
    lam = jnp.stack([a_parts[_UPPER.index((i, i))] * scale for i in range(_N)], axis=-1)
    vecs = jnp.stack([jnp.stack(v_parts[_N * i : _N * (i + 1)], axis=-1) for i in range(_N)], axis=-2)
    return lam, vecs
