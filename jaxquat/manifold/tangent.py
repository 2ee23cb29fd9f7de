"""Optimisation on the rotation manifold: tangent-space gradients and optax-compatible updates.

A loss ``L(q)`` of a unit quaternion has a Euclidean gradient ``g = dL/dq``
(``(..., 4)``); the gradient with respect to a body rotation ``q -> q Exp(d)``
at ``d = 0`` is the 3-vector ``1/2 vec(q* g)`` (space: ``1/2 vec(g q*)``).
:func:`tangent_optimizer` wraps any optax ``GradientTransformation`` so that it
sees these 3-vectors, and :func:`apply_tangent_updates` applies its updates
with :func:`jaxquat.plus` instead of ``+``, so quaternions stay unit without
renormalisation. Non-quaternion leaves (marked ``False`` in ``mask``) are passed
through unchanged, so one optimiser can train attitudes and other parameters.

Usage::

    opt = jq.tangent_optimizer(optax.adam(1e-2))
    state = opt.init(params)
    grads = jax.grad(loss)(params)
    updates, state = opt.update(grads, state, params)
    params = jq.apply_tangent_updates(params, updates)

The optimiser's moments are kept in the tangent space of the current point and
are not parallel-transported between steps (the usual first-order choice).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _checks, _rates
from .lie import plus

__all__ = ["tangent_gradient", "tangent_gradients", "tangent_optimizer", "apply_tangent_updates"]


def tangent_gradient(
    q: Float[ArrayLike, "*#batch 4"], grad: Float[ArrayLike, "*#batch 4"], frame: str = "body"
) -> Float[Array, "*batch 3"]:
    """The gradient of a loss with respect to a rotation of ``q``, from its Euclidean gradient.

    ``d/dd L(q Exp(d)) |_{d=0} = 1/2 vec(q* g)`` (body) and
    ``d/dd L(Exp(d) q) |_{d=0} = 1/2 vec(g q*)`` (space), with ``g = dL/dq``.
    The component of ``g`` along ``q`` (which only changes ``|q|``) drops out.
    """
    frame = _checks.frame(frame)
    q, grad = _checks.arguments(q=(q, "quaternion"), grad=(grad, "quaternion"))
    return 0.5 * _rates.vec_rate(q, grad, frame)  # the same map as a generalised force -> torque


def _mask_tree(params: Any, mask: Any) -> Any:
    if mask is None:
        return jax.tree.map(lambda _: True, params)
    if callable(mask):
        return mask(params)
    return mask


def tangent_gradients(params: Any, grads: Any, mask: Any = None, frame: str = "body") -> Any:
    """:func:`tangent_gradient` on the quaternion leaves of a pytree; other leaves pass through.

    ``mask`` as in :func:`tangent_optimizer` (``None``: every leaf is a quaternion array).
    """
    m = _mask_tree(params, mask)
    return jax.tree.map(lambda is_q, g, p: tangent_gradient(p, g, frame) if is_q else g, m, grads, params)


def tangent_optimizer(base: Any, mask: Any = None, frame: str = "body") -> optax.GradientTransformation:
    """Wrap an optax ``GradientTransformation`` to optimise quaternion leaves in the tangent space.

    ``mask``: ``None`` (every leaf of the parameter pytree is a quaternion array
    ``(..., 4)``), a pytree of booleans with the structure of the parameters, or a
    function ``params -> that pytree`` (as in ``optax.masked``). ``update`` takes
    Euclidean gradients and returns updates that are 3-vectors on quaternion
    leaves (to be applied with :func:`apply_tangent_updates`) and ordinary updates
    elsewhere. Returns an ``optax.GradientTransformation`` whose ``update`` needs ``params``
    (the tangent space is that of the current quaternions); without them it raises.
    """
    frame = _checks.frame(frame)
    if not (hasattr(base, "init") and hasattr(base, "update")):
        raise TypeError(f"argument 'base' must be an optax GradientTransformation, got {type(base).__name__}")

    def tangent_params(params):
        m = _mask_tree(params, mask)
        return jax.tree.map(lambda is_q, p: jnp.zeros(p.shape[:-1] + (3,), p.dtype) if is_q else p, m, params)

    def init(params):
        return base.init(tangent_params(params))

    def update(updates, state, params=None):  # updates: the Euclidean gradients
        if params is None:
            raise ValueError("tangent_optimizer's update needs 'params' (the quaternions the gradients are taken at)")
        return base.update(tangent_gradients(params, updates, mask, frame), state, tangent_params(params))

    return optax.GradientTransformation(init, update)


def apply_tangent_updates(params: Any, updates: Any, mask: Any = None, frame: str = "body") -> Any:
    """``plus(q, u)`` on quaternion leaves, ``p + u`` on the others (the analogue of ``optax.apply_updates``)."""
    frame = _checks.frame(frame)
    m = _mask_tree(params, mask)
    return jax.tree.map(lambda is_q, p, u: plus(p, u, frame) if is_q else p + u, m, params, updates)
