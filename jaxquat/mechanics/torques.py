"""External torque models: user torque functions and the gravity-gradient torque.

A torque function has the signature ``fn(t, q, omega, args) -> torque`` with
``q`` shaped ``(..., 4)``, ``omega`` and the result ``(..., 3)``. It is written
in one frame: a *body* torque function receives the body angular velocity and
returns a body-frame torque; a *space* torque function receives and returns
space-frame vectors. :func:`as_body_torque` turns either into a body torque
function, the form the dynamics and the simulators consume. Torque functions
must be JAX-traceable (they run inside ``jit`` and under ``grad``); their
parameters go in ``args`` (any pytree) so they can be differentiated.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from .. import _arrays, _checks, _quaternion, _rates, _trig

__all__ = ["as_body_torque", "gravity_gradient_torque", "circular_orbit_gravity_gradient"]

TorqueFn = Callable[[Any, Array, Array, Any], Array]


def as_body_torque(fn: TorqueFn, frame: str = "body") -> TorqueFn:
    """Wrap a torque function written in ``frame`` as a body-frame torque function.

    For ``frame="space"`` the wrapper calls ``fn(t, q, rotate(q, w_b), args)``
    and returns ``rotate(conjugate(q), M_s)`` ([S] eq. (25) relates both to the
    same generalised force). The result's shape is checked when traced: a
    torque function that returns anything but ``(..., 3)`` raises ``ValueError``
    naming it.
    """
    frame = _checks.frame(frame)
    if not callable(fn):
        raise TypeError(f"argument 'fn' must be a torque function fn(t, q, omega, args), got {type(fn).__name__}")

    def body_torque(t, q, omega, args=None):
        if frame == "body":
            out = fn(t, q, omega, args)
        else:
            out = _quaternion.rotate(_quaternion.conjugate(q), fn(t, q, _quaternion.rotate(q, omega), args))
        name = getattr(fn, "__name__", "torque function")
        return _checks.vec3(out, f"{name}(t, q, omega, args)")

    return body_torque


def gravity_gradient_torque(
    q: Float[ArrayLike, "*#batch 4"],
    position: Float[ArrayLike, "*#batch 3"],
    inertia: Float[ArrayLike, "*#batch 3 3"],
    mu: float | Array = 1.0,
) -> Float[Array, "*batch 3"]:
    """Gravity-gradient torque on a body in a central inverse-square field (body frame).

    ``M_b = 3 mu / |r|^5 (r_b x I r_b)`` with ``r_b = A^T r`` the position of the
    centre of mass relative to the attracting centre, resolved in the body frame
    (``position`` is given in the space frame), ``I`` the body inertia and
    ``mu`` the gravitational parameter. It is minus the derivative of the
    potential ``V = -mu/(2|r|^3) (tr I - 3 r_b.I r_b/|r|^2)`` with respect to a
    body-frame rotation (tested). Assumes ``|q| = 1``.
    """
    mu = _checks.scalar_like(mu, "mu")
    if mu.ndim == 0 and mu.weak_type:  # a Python number: used as it is (a weak scalar takes the others' dtype)
        q, r, inertia = _checks.arguments(
            q=(q, "quaternion"), position=(position, "vector"), inertia=(inertia, "inertia"), shared=("inertia",)
        )
    else:
        q, r, inertia, mu = _checks.arguments(
            q=(q, "quaternion"),
            position=(position, "vector"),
            inertia=(inertia, "inertia"),
            mu=(mu, "scalar"),
            shared=("inertia",),
        )
    return _arrays.compiled_rows(_gravity_gradient_torque, (1, 1, 2, 0), q, r, inertia, mu)


def _gravity_gradient_torque(q: Array, r: Array, inertia: Array, mu: Array) -> Array:
    # On components, as the dynamics (jaxquat.mechanics.dynamics). Rows -> components (session 53,
    # one core, least of 5): the gradient in q at 10^5, float32 6.3 -> 0.41 ms, float64 23.7 ->
    # 0.74 ms; as the torque of simulate's scan path (circular_orbit_gravity_gradient, 1000 bodies
    # x 1000 RKMK4 steps, float32) the forward pass 160 -> 16 ms, its gradient 291-308 -> 100-104 ms.
    qc, rc = _arrays.components(q), _arrays.components(r)
    rb = _rates.rotate_parts(qc, rc, inverse=True)
    rsq = _rates.dot_parts(rc, rc)
    coeff = 3.0 * mu / (rsq * rsq * jnp.sqrt(rsq))
    torque = _rates.cross_parts(rb, _rates.matvec_parts(_rates.matrix_entries(inertia), rb))
    return _arrays.stack_in_one_loop([coeff * x for x in torque])


def circular_orbit_gravity_gradient(inertia: Float[ArrayLike, "3 3"], mean_motion: float | Array) -> TorqueFn:
    """Body torque function ``fn(t, q, omega, args)`` for gravity gradient on a circular orbit.

    The orbit lies in the space frame's x-y plane; the unit radial direction at
    time ``t`` is ``e_r = (cos n t, sin n t, 0)`` with ``n`` the mean motion
    (``n^2 = mu / R^3``), so ``M_b = 3 n^2 (e_b x I e_b)``, ``e_b = A^T e_r``.
    The orbit frame (x radial, y along-track, z orbit normal) at time ``t`` is
    the quaternion ``from_rotvec((0, 0, n t))``; a body with principal axes
    along it and ``omega_b = (0, 0, n)`` is in equilibrium, and small pitch
    oscillations about z have angular frequency ``n sqrt(3 (I_yy - I_xx) / I_zz)``
    (the worked example in ``tests/test_torques.py``).
    """
    inertia = _checks.inertia(inertia)
    n = _checks.scalar_like(mean_motion, "mean_motion")

    def gravity_gradient(t, q, omega, args=None):
        t = jnp.asarray(t, dtype=q.dtype)
        s, c = _trig.sincos(n * t)
        e_r = jnp.stack([c, s, jnp.zeros_like(t)], axis=-1)
        e_r = jnp.broadcast_to(e_r, q.shape[:-1] + (3,))
        return gravity_gradient_torque(q, e_r, inertia, n * n)

    return gravity_gradient
