"""Integrating the equations of motion: the Lie-group (RKMK) solvers for diffrax, the splitting
methods, the fixed-step scan driver and ``simulate``.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
