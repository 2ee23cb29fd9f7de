"""Attitude estimation: the multiplicative extended Kalman filter and the unscented filter on the
group.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
