"""Calculus on the rotation group: plus/minus, the Jacobians of Exp, tangent-space gradients and
optax updates, slerp/squad and the C2 rotation spline.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
