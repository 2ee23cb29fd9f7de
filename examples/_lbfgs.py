"""A fixed number of optax L-BFGS iterations in one jitted lax.scan (shared by the examples)."""

from __future__ import annotations

import jax
import optax


def minimize(f, x0, iters: int):
    """Run ``iters`` L-BFGS steps (optax's zoom line search) on ``f`` from ``x0`` (any pytree).

    Returns the final parameters and the objective value at every iteration. Call it inside
    ``jax.jit`` so the loop compiles once.
    """
    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(f)

    def body(carry, _):
        x, state = carry
        value, grad = value_and_grad(x, state=state)
        updates, state = opt.update(grad, state, x, value=value, grad=grad, value_fn=f)
        return (optax.apply_updates(x, updates), state), value

    (x, _), values = jax.lax.scan(body, (x0, opt.init(x0)), None, length=iters)
    return x, values
