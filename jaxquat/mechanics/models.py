"""Vehicle models with quaternion leaves: diffrax vector fields for the Lie solvers' ``quaternions=``.

Each model is an ``equinox.Module`` (its parameters are differentiable leaves) whose call
``model(t, y, args)`` returns the time derivative of the state dict ``y``, with the ordinary
``qdot = 1/2 q (0, w_b)`` on the quaternion leaf ([S] eq. (16), [T] eq. (47b)); its class
attribute ``quaternions`` is the mask for the solver::

    model = jq.Quadrotor(mass=1.2, inertia=jnp.diag(jnp.array([0.02, 0.03, 0.05])), control=control)
    diffrax.diffeqsolve(diffrax.ODETerm(model), jq.RKMK45(quaternions=jq.Quadrotor.quaternions), ...)

The inputs come from ``control(t, y, args)``, a function the user gives (a feedback law, a
schedule, a neural network); ``args`` of ``diffeqsolve`` are passed to it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax import Array

from .. import _arrays, _checks, _quaternion, _rates
from .inertia import validated

__all__ = ["Quadrotor", "ReactionWheelSpacecraft"]


def _control(control: Any) -> Callable:
    if not callable(control):
        raise TypeError(f"argument 'control' must be a function control(t, y, args), got {type(control).__name__}")
    return control


def _positive(x: Any, name: str) -> Array:
    arr = _checks.scalar_like(x, name)
    if arr.ndim != 0:
        raise ValueError(f"argument '{name}' must be a scalar, got shape {tuple(arr.shape)}")
    value = _checks.concrete(arr)
    if value is not None and not value > 0:
        raise ValueError(f"argument '{name}' must be positive, got {float(value)}")
    return arr


class Quadrotor(eqx.Module):
    """A quadrotor: position ``r`` and velocity ``v`` (inertial frame), attitude ``q`` (body to
    inertial, active: ``v_inertial = q v_body q*``) and body rate ``w``; state
    ``{"r": (3,), "v": (3,), "q": (4,), "w": (3,)}``::

        r' = v
        v' = (T / m) R(q) e_z - g e_z - c v        (thrust T along body z, linear drag c)
        q' = 1/2 q (0, w)                          ([S] eq. (16))
        w' = I^-1 (M - w x I w)                    (Euler, [S] eq. (19))

    ``control(t, y, args) -> (thrust (), torque (3,))``: thrust in newtons along body z, torque
    in the body frame. ``inertia``: body tensor ``(3, 3)`` (validated as
    :class:`jaxquat.RigidBody`'s); ``mass``, ``drag`` (per unit mass, 1/s) and ``gravity``
    (m/s^2, along inertial ``-z``) are scalars. Use ``quaternions=Quadrotor.quaternions``.
    """

    mass: Array
    inertia: Array
    control: Callable
    drag: Array
    gravity: Array
    quaternions: ClassVar[dict[str, bool]] = {"r": False, "v": False, "q": True, "w": False}

    def __init__(self, mass: Any, inertia: Any, control: Callable, drag: Any = 0.0, gravity: Any = 9.81):
        self.mass = _positive(mass, "mass")
        self.inertia = validated(inertia)
        self.control = _control(control)
        self.drag = _checks.scalar_like(drag, "drag")
        self.gravity = _checks.scalar_like(gravity, "gravity")

    def __call__(self, t, y: dict[str, Array], args) -> dict[str, Array]:
        return _with_qdot(y, self.body_rate_field(t, y, args))

    def body_rate_field(self, t, y: dict[str, Array], args) -> dict[str, Array]:
        """The field with the body rate ``w`` (body frame) in place of ``dq/dt = q (0, w)/2``
        ([S] eq. (16)): the form the Lie solvers step in."""
        q, v, w = y["q"], y["v"], y["w"]
        thrust, torque = self.control(t, y, args)
        up = jnp.zeros_like(v).at[..., 2].set(1)
        accel = (
            (jnp.asarray(thrust, v.dtype)[..., None] / self.mass) * _quaternion.rotate(q, up)
            - self.gravity * up
            - self.drag * v
        )
        return {
            "r": v,
            "v": accel,
            "q": w,
            "w": _rates.euler_body(self.inertia, w, torque),
        }


class ReactionWheelSpacecraft(eqx.Module):
    """A spacecraft with reaction wheels (a gyrostat): attitude ``q`` (body to inertial), body
    rate ``w`` and the wheels' axial angular momenta ``h`` ``(n,)`` (each wheel's whole axial
    momentum, body spin included); state ``{"q": (4,), "w": (3,), "h": (n,)}``. With ``A``
    ``(3, n)`` the spin axes as columns and ``J`` the inertia of the spacecraft *without* the
    wheels' axial inertias (``J = J_locked - sum_i J_s,i a_i a_i^T``), the total body momentum
    is ``H = J w + A h`` and::

        q' = 1/2 q (0, w)                          ([S] eq. (16))
        h' = u                                     (u: motor torques on the wheels)
        J w' = M_ext - A u - w x (J w + A h)       (d/dt of R(q) H = R(q) M_ext)

    Derived here from the conservation of ``R(q) H`` (Euler's equations, [S] eq. (19), with
    the wheels' momentum added to the body's; the textbook gyrostat), and checked in the
    tests: without ``M_ext`` the inertial momentum ``R(q) H`` is constant whatever ``u``.

    ``control(t, y, args) -> (u (n,), M_ext (3,))``: commanded wheel torques and the external
    body-frame torque. Limits: ``wheel_torque_limit`` clips ``u`` to ``[-u_max, u_max]``;
    ``wheel_momentum_limit`` ``h_max`` stops a wheel's torque while ``|h_i| >= h_max`` and the
    torque would drive ``|h_i|`` further (a hard stop; the field is then discontinuous, so
    adaptive solvers locate the switch by shrinking the step). Each is a scalar or ``(n,)``;
    None: no limit. Use ``quaternions=ReactionWheelSpacecraft.quaternions``. ``axes`` ``(n, 3)``
    are normalised; a zero row raises when the values are known (an eager call) and gives NaN
    under ``jit``, as elsewhere in the library.
    """

    inertia: Array
    axes: Array
    control: Callable
    wheel_torque_limit: Array | None
    wheel_momentum_limit: Array | None
    quaternions: ClassVar[dict[str, bool]] = {"q": True, "w": False, "h": False}

    def __init__(
        self,
        inertia: Any,
        axes: Any,
        control: Callable,
        wheel_torque_limit: Any = None,
        wheel_momentum_limit: Any = None,
    ):
        self.inertia = validated(inertia)
        axes = _checks.as_float_array(axes, "axes")
        if axes.ndim != 2 or axes.shape[1] != 3 or axes.shape[0] < 1:
            raise ValueError(
                f"argument 'axes' must be the wheels' spin axes shaped (n, 3), n >= 1, got shape {tuple(axes.shape)}"
            )
        norms = jnp.linalg.norm(axes, axis=-1, keepdims=True)
        lengths = _checks.concrete(norms[:, 0])
        if lengths is not None and not (lengths > 0).all():
            raise ValueError(f"argument 'axes' must be nonzero spin axes, got rows of length {lengths.tolist()}")
        self.axes = axes / norms
        self.control = _control(control)
        self.wheel_torque_limit = (
            None if wheel_torque_limit is None else _limit(wheel_torque_limit, "wheel_torque_limit", axes)
        )
        self.wheel_momentum_limit = (
            None if wheel_momentum_limit is None else _limit(wheel_momentum_limit, "wheel_momentum_limit", axes)
        )

    def wheel_torque(self, u: Array, h: Array) -> Array:
        """The commanded wheel torques ``u`` after the torque and momentum limits."""
        if self.wheel_torque_limit is not None:
            u = jnp.clip(u, -self.wheel_torque_limit, self.wheel_torque_limit)
        if self.wheel_momentum_limit is not None:
            u = jnp.where((jnp.abs(h) >= self.wheel_momentum_limit) & (u * h > 0), 0, u)
        return u

    def momentum(self, y: dict[str, Array]) -> Array:
        """The total angular momentum in the inertial frame, ``R(q) (J w + A h)``."""
        return _quaternion.rotate(y["q"], _arrays.matvec(self.inertia, y["w"]) + _arrays.matmul(y["h"], self.axes))

    def __call__(self, t, y: dict[str, Array], args) -> dict[str, Array]:
        return _with_qdot(y, self.body_rate_field(t, y, args))

    def body_rate_field(self, t, y: dict[str, Array], args) -> dict[str, Array]:
        """The field with the body rate ``w`` (body frame) in place of ``dq/dt = q (0, w)/2``
        ([S] eq. (16)): the form the Lie solvers step in."""
        w, h = y["w"], y["h"]
        u, external = self.control(t, y, args)
        u = self.wheel_torque(jnp.asarray(u, h.dtype), h)
        total = _arrays.matvec(self.inertia, w) + _arrays.matmul(h, self.axes)
        wdot = _arrays.symmetric_solve(self.inertia, external - _arrays.matmul(u, self.axes) - jnp.cross(w, total))
        return {"q": w, "w": wdot, "h": u}


def _with_qdot(y: dict[str, Array], field: dict[str, Array]) -> dict[str, Array]:
    """A body-rate field's values with ``dq/dt = q (0, w)/2`` on the attitude leaf."""
    return {**field, "q": _rates.qdot_from_omega(y["q"], field["q"], "body")}


def _limit(x: Any, name: str, axes: Array) -> Array:
    arr = _checks.as_float_array(x, name)
    if arr.shape not in ((), (axes.shape[0],)):
        raise ValueError(
            f"argument '{name}' must be a scalar or shaped (n,) = ({axes.shape[0]},), got shape {tuple(arr.shape)}"
        )
    value = _checks.concrete(arr)
    if value is not None and not (value > 0).all():
        raise ValueError(f"argument '{name}' must be positive, got {value}")
    return arr
