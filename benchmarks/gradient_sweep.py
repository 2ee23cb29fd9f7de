"""Every public function's value and gradient at 10^5 rows on one core: the registry of
``tests/test_contract.py`` (each function, its argument kinds and the argument it is
differentiated in), the gradient of ``sum(f * W)`` for a fixed random ``W``, least of 7 calls
after compilation. A survey for outliers (a gradient many times its value), not a comparison
with peers, so ``make bench`` does not run it (about two minutes per dtype).

    taskset -c 0 .venv/bin/python benchmarks/gradient_sweep.py float32 [name ...]

Prints one row per function: value (ms), gradient (ms), their ratio.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> None:
    dtype_name, only = (argv[0] if argv else "float32"), set(argv[1:])
    os.environ["JAX_ENABLE_X64"] = "1" if dtype_name == "float64" else "0"
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    import jax
    import jax.numpy as jnp
    import numpy as np
    import test_contract as contract

    dtype = jnp.dtype(dtype_name)
    rows = int(os.environ.get("ROWS", 100_000))
    rng = np.random.default_rng(0)
    q = contract._unit(rng.normal(size=(rows, 4)))
    for name, (fn, kinds, diff) in contract.REGISTRY.items():
        if (only and name not in only) or diff is None:
            continue
        try:
            args = [jnp.asarray(contract._args(kind, q), dtype) for kind in kinds]
        except KeyError:
            continue  # a kind the registry forms elsewhere
        weights = [jnp.asarray(rng.normal(size=x.shape), x.dtype) for x in jax.tree.leaves(jax.eval_shape(fn, *args))]

        def loss(x, args=args, fn=fn, diff=diff, weights=weights):
            a = list(args)
            a[diff] = x
            return sum(jnp.sum(y * w) for y, w in zip(jax.tree.leaves(fn(*a)), weights))

        value = _least(jax.jit(fn), *args)
        grad = _least(jax.jit(jax.grad(loss)), args[diff])
        print(f"{name:40s} {value:8.2f} {grad:8.2f} {grad / value:6.1f}x", flush=True)


def _least(fn, *args, repeats: int = 7) -> float:
    import jax

    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return 1e3 * min(times)


if __name__ == "__main__":
    main(sys.argv[1:])
