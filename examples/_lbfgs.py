"""L-BFGS for the examples: a fixed number of optax L-BFGS iterations in one jitted lax.scan.

The loop itself is jaxquat's own (the one minimum_time_reorientation runs); this module
only gives it the name the examples use.
"""

from __future__ import annotations

from jaxquat.time_optimal import _lbfgs


def minimize(f, x0, iters: int):
    """Run ``iters`` L-BFGS steps (optax's zoom line search) on ``f`` from ``x0`` (any pytree).

    Returns the final parameters and the objective value at every iteration. Call it inside
    ``jax.jit`` so the loop compiles once.
    """
    return _lbfgs(f, x0, iters)
