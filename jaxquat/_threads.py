"""XLA's threads on the CPU: the compiler options that keep a small batch's loops on one thread.

XLA's CPU compiler (jaxlib 0.10.2) splits an element-wise kernel between the threads of its pool
when a cost model says the kernel is worth it (its pass ``cpu-parallel-task-assigner``: about a
cycle per floating-point operation and ten per byte accessed, at least 100 000 cycles per
thread). The model counts unvectorised cycles, so it splits kernels of a microsecond or two: at
1000 bodies four of the 19 kernels of ``simulate``'s RKMK4 scan step (float32) are split in two
on a 2-core machine, and handing half of one to the other thread and waiting for it costs more
than the half saves, at every step. Which kernels it splits, and what the split costs, depend on
the program and its dtype. Measured (session 67, a 2-core AMD EPYC, jaxlib 0.10.2; ``jax.jit``
of ``simulate``'s scan path, torque-free, 1000 RKMK4 steps; the two programs' calls interleaved,
median of 7-15; XLA's default time over the time with the pass off, above 1: one thread faster):

| float32 | 250 | 500 | 1000 | 2000 | 4000 |
|---|---:|---:|---:|---:|---:|
| forward | 3.30 | 4.18 | 2.09 | 2.44 | 2.10 |
| ``grad`` | 1.22 | 1.47 | 1.10 | 1.05 | 0.85 |
| ``jvp`` | 2.55 | 1.51 | 1.26 | 0.86 | 0.67 |

| float64 | 250 | 500 | 1000 | 2000 | 4000 |
|---|---:|---:|---:|---:|---:|
| forward | 2.28 | 0.99 | 0.83 | 0.77 | 1.21 |
| ``grad`` | 0.91 | 0.89 | 0.97 | 0.88 | 0.86 |
| ``jvp`` | 1.93 | 1.09 | 0.87 | 0.62 | 0.60 |

(1000 float32 bodies: forward 6.5 against 13.7 ms, ``grad`` 23.3 against 25.7 ms, one ``jvp``
12.8 against 16.1 ms; on one pinned core, where XLA splits nothing, the forward pass takes
6.3 ms.) So the option is for float32 batches of up to :data:`SMALL_BATCH` bodies. The values
are the same to the bit either way (the split divides a loop's elements, not its arithmetic).

A library cannot choose for a program it does not compile: JAX takes ``compiler_options`` on a
top-level ``jax.jit`` only (a nested one raises ``ValueError``). :func:`cpu_compiler_options`
gives a user the options for their own ``jit``; ``simulate`` uses them when it compiles its own
program (an eager call).
"""

from __future__ import annotations

import functools
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["cpu_compiler_options"]

# The most float32 bodies (elements of a batch) for which one thread per kernel was measured to
# be faster in the forward pass, ``grad`` and ``jvp`` alike (the module docstring's tables).
SMALL_BATCH = 1024

# The options themselves: XLA's pass that splits kernels between threads, switched off (shared with
# benchmarks/simulation.py, which measures them where cpu_compiler_options does not pick them).
ONE_THREAD = {"xla_disable_hlo_passes": "cpu-parallel-task-assigner"}


def cpu_compiler_options(batch: int, dtype=np.float32, *, devices: int = 1) -> dict[str, str]:
    """XLA options for ``jax.jit(fn, compiler_options=...)`` of a program that steps ``batch``
    bodies (or rotates ``batch`` quaternions) at once in ``dtype``: on the CPU backend, for a
    float32 (or narrower) batch of at most 1024, or a program on more than one CPU device
    (``devices``), XLA's pass that splits each element-wise kernel between threads switched off
    (``xla_disable_hlo_passes``); ``{}`` otherwise (float64 or a larger batch on one device, a GPU
    or TPU).

    Every loop of the program then runs on the calling thread. XLA's cost model splits kernels of
    a microsecond or two, and waiting for the second thread costs more than it saves:
    ``simulate``'s fixed-step scan path at 1000 float32 bodies x 1000 RKMK4 steps (a 2-core CPU,
    medians) runs its forward pass in 6.5 instead of 13.7 ms, its gradient in 23.3 instead of
    25.7 ms and one ``jvp`` in 12.8 instead of 16.1 ms. In float64, and from about 2000 float32
    bodies, XLA's split gains in some of these and is kept (``jaxquat._threads`` has the tables).
    The results are the same to the bit. Pass the options to a top-level ``jax.jit`` only (JAX
    refuses them on a nested one); they replace any ``--xla_disable_hlo_passes`` of ``XLA_FLAGS``
    for that program.

    ``devices``: the number of CPU devices the program runs on at once (a ``jax.shard_map`` or a
    sharded ``jit`` over ``jax.config.update("jax_num_cpu_devices", n)``'s devices). With more than
    one, the pass is off for any batch and dtype: each device already keeps a core busy, and a
    device that hands half a kernel to a thread the other device is using waits for it. 10^5
    torque-free bodies x 1000 RKMK4 steps in a ``shard_map`` over 2 CPU devices of a 2-core AMD
    EPYC (:func:`jaxquat.simulate`'s chunks of 2000 bodies there), min of 3, XLA's default -> the
    pass off: float32 forward 332 -> 294 ms, gradient 1363 -> 1264 ms; float64 602 -> 593 ms and
    2638 -> 2471 ms; with chunks of 20 000 float32 bodies 2283 -> 293 ms and 9261 -> 1821 ms
    (session 68; unsharded on one device 361 and 2997 ms). Session 69, a busier run: float32
    401 -> 334-345 ms and 1569 -> 1294-1355 ms, float64 699 -> 679 ms and 2907 -> 2832 ms;
    one device 538 and 4062 ms (float64 937 and 6007 ms).

    Example::

        step = jax.jit(loss_and_grad, compiler_options=jq.cpu_compiler_options(1000, jnp.float32))
    """
    if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 0:
        raise ValueError(f"argument 'batch' must be a number of bodies (an int >= 0), got {batch!r}")
    if isinstance(devices, bool) or not isinstance(devices, (int, np.integer)) or devices < 1:
        raise ValueError(f"argument 'devices' must be a number of devices (an int >= 1), got {devices!r}")
    if jax.default_backend() != "cpu":
        return {}
    if devices > 1 or (batch <= SMALL_BATCH and np.dtype(dtype).itemsize <= 4):
        return dict(ONE_THREAD)
    return {}


@functools.cache
def batch_multiple() -> int:
    """The number of bodies a batch of ``simulate`` is padded to a multiple of on the CPU: the
    threads of XLA's pool (the CPUs this process may run on, as XLA counts them) and their next
    power of two, their least common multiple (2 threads: 2, 4: 4, 6: 24, 8: 8, 16: 16); 1 on
    one thread or another backend.

    Why: XLA's CPU compiler (jaxlib 0.10.2) splits a kernel over a batch axis into ``p`` parts
    (its pass ``cpu-parallel-task-assigner``, ``p`` up to the pool's size); when ``p`` does not
    divide that axis, the parts differ by one element and the kernel runs about three times
    slower. The compiled HLO is the same as for an even axis; why the code is slower was not
    found. Parts of whole rows of a wide axis are not slowed: ``(3, 667)`` split as 1 and 2 rows
    ran at the speed of ``(2000,)``, ``(667, 3)`` three times slower. On one pinned core nothing
    is split and an odd batch costs what an even one does. Measured on a 2-core Intel Xeon
    (``p = 2``; ``docs/integrators.md``, "An uneven split"), in a caller's ``jit``, float32, an
    odd batch unpadded -> padded: ``simulate``'s closed form over 101 saved times at 1001 bodies
    32.6-33.8 -> 10.3-10.6 ms (1000 bodies: 10.0-10.5 ms); the RKMK4 scan path (1000 steps) at
    1001 bodies forward 40.9-43.0 -> 18.1-22.5 ms and gradient 95 -> 51-54 ms, at 10^5 + 1
    bodies 2890 -> 798 ms and 10478 -> 5311 ms. A part count that is not a divisor of this
    multiple (3 of 8 threads, say) still meets the uneven split: the multiple covers every count
    on 2 threads and the power-of-two counts on more."""
    threads = pool_threads()
    return 1 if threads <= 1 else math.lcm(threads, 1 << (threads - 1).bit_length())


@functools.cache
def pool_threads() -> int:
    """The threads XLA's CPU client splits a kernel between: the CPUs this process may run on
    (``os.sched_getaffinity``, which XLA reads too); 1 on another backend."""
    if jax.default_backend() != "cpu":
        return 1
    affinity = getattr(os, "sched_getaffinity", None)
    return max(1, len(affinity(0)) if affinity is not None else os.cpu_count() or 1)


def padded_batch(n: int, multiple: int) -> int:
    """``n`` bodies rounded up to a multiple of ``multiple`` (:func:`batch_multiple`); a single
    body is left as it is."""
    return n if n <= 1 else -(-n // multiple) * multiple


def with_copies_of_first(x, total: int):
    """``x`` (bodies on its first axis) followed by copies of its first body, ``total`` in all:
    the padding of a batch to :func:`padded_batch`'s size, whose results are dropped."""
    pad = total - x.shape[0]
    return jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad,) + x.shape[1:])]) if pad else x


def in_shard_map() -> bool:
    """Whether the code being traced is the body of a ``jax.shard_map`` (some axis of the mesh is
    manual: each device runs this code on its own shard). Read from
    ``jax.sharding.get_abstract_mesh()``; a JAX without it answers ``False``."""
    get = getattr(jax.sharding, "get_abstract_mesh", None)
    if get is None:  # pragma: no cover - a JAX before 0.5
        return False
    return bool(getattr(get(), "manual_axes", ()))


def split_across_devices(x) -> bool:
    """Whether the type of ``x`` says it is split between devices: some axis sharded over a mesh
    axis of more than one device that is not manual (``jax.sharding.AxisType.Explicit``, the
    default of ``jax.make_mesh``; inside a ``jax.shard_map`` each device's shard is whole, and
    under ``AxisType.Auto`` axes the type does not say, so both answer ``False``). Read from
    ``jax.typeof(x).sharding``; a JAX without it answers ``False``."""
    typeof = getattr(jax, "typeof", None)
    if typeof is None:  # pragma: no cover - a JAX before 0.6
        return False
    sharding = getattr(typeof(x), "sharding", None)
    spec, mesh = getattr(sharding, "spec", None), getattr(sharding, "mesh", None)
    if spec is None or mesh is None:
        return False
    manual = set(getattr(mesh, "manual_axes", ()))
    names = [n for entry in spec if entry is not None for n in (entry if isinstance(entry, tuple) else (entry,))]
    return any(mesh.shape[n] > 1 and n not in manual for n in names)


def at_top_level() -> bool:
    """Whether JAX is evaluating eagerly here, outside any ``jit``, ``vmap`` or ``grad``: where a
    ``jax.jit`` with ``compiler_options`` may be called (JAX raises ``ValueError`` for one staged
    into a caller's ``jit``, whose arguments may all be concrete, e.g. NumPy constants). Read
    from JAX's trace state (``jax._src.core.trace_state_clean``, no public API); where a JAX
    version lacks it, ``False``: the options are then never passed, which only costs speed."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:  # pragma: no cover - a JAX without it
        return False
    return bool(trace_state_clean())
