"""XLA's threads on the CPU (``jaxquat._threads``): the options that keep a small float32 batch's
loops on one thread, the same values with them, and ``simulate`` using them eagerly only."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from helpers import DTYPE, ChunkSeen, spy_on_chunk_sizes

OPTIONS = {"xla_disable_hlo_passes": "cpu-parallel-task-assigner"}
I_DIAG = np.diag([1.0, 2.0, 3.0])
TS = np.asarray([0.0, 0.1])


def _bodies(n: int):
    rng = np.random.default_rng(5)
    return jq.normalize(jnp.asarray(rng.normal(size=(n, 4)), DTYPE)), jnp.asarray(rng.normal(size=(n, 3)), DTYPE)


def _final_attitudes(q0, w0):
    return jq.simulate(q0, w0, I_DIAG.astype(q0.dtype), TS, solver=jq.RKMK4(), dt0=0.01).q[:, -1]


def test_the_options_are_for_small_float32_batches_on_the_cpu():
    """On the CPU: the pass off for float32 (and narrower) batches of up to 1024, nothing for float64
    or a larger batch (XLA's split gained there: ``jaxquat._threads``'s tables)."""
    assert jax.default_backend() == "cpu"
    assert jq.cpu_compiler_options(1, jnp.float32) == OPTIONS
    assert jq.cpu_compiler_options(1024, np.float32) == OPTIONS
    assert jq.cpu_compiler_options(1000, jnp.float16) == OPTIONS
    assert jq.cpu_compiler_options(1000) == OPTIONS  # float32 by default
    assert jq.cpu_compiler_options(1025, jnp.float32) == {}
    assert jq.cpu_compiler_options(10, jnp.float64) == {}


def test_a_program_on_several_cpu_devices_keeps_each_device_on_one_thread():
    """With ``devices`` > 1 the pass is off for any batch and dtype (each device keeps a core busy;
    ``cpu_compiler_options``' docstring has the figures), and one device keeps the batch rule."""
    assert jq.cpu_compiler_options(100_000, jnp.float32, devices=2) == OPTIONS
    assert jq.cpu_compiler_options(10, jnp.float64, devices=16) == OPTIONS
    assert jq.cpu_compiler_options(100_000, jnp.float32, devices=1) == {}
    assert jq.cpu_compiler_options(10, jnp.float32, devices=np.int64(1)) == OPTIONS


@pytest.mark.parametrize("bad", [-1, 2.5, "1000"])
def test_a_batch_that_is_not_a_count_is_refused(bad):
    with pytest.raises(ValueError, match="argument 'batch'"):
        jq.cpu_compiler_options(bad)


@pytest.mark.parametrize("bad", [0, 1.0, True, None])
def test_a_device_count_that_is_not_a_positive_int_is_refused(bad):
    with pytest.raises(ValueError, match="argument 'devices'"):
        jq.cpu_compiler_options(10, devices=bad)


def test_simulate_inside_shard_map_solves_in_the_shard_map_chunks(monkeypatch):
    """The scan path's chunks hold ``_CHUNK_BYTES`` per component array outside a ``shard_map``
    and ``_SHARD_MAP_CHUNK`` bodies inside one (``in_shard_map``: a manual mesh axis; a mesh of the
    one device here, which is manual all the same). A spy on ``_in_chunks`` records the chunk size
    and stops: nothing is solved or compiled."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxquat import _threads
    from jaxquat.integration import numerical_solve

    sizes = spy_on_chunk_sizes(monkeypatch)
    monkeypatch.setattr(numerical_solve, "_CHUNK_BYTES", 3 * np.dtype(DTYPE).itemsize)
    monkeypatch.setattr(numerical_solve, "_SHARD_MAP_CHUNK", 2)
    q0, w0 = _bodies(5)
    mesh = jax.make_mesh((1,), ("b",))
    inside = []

    def body(q, w):
        inside.append(_threads.in_shard_map())
        return _final_attitudes(q, w)

    assert not _threads.in_shard_map()
    with pytest.raises(ChunkSeen):
        _final_attitudes(q0, w0)
    sharded = [jax.device_put(x, NamedSharding(mesh, P("b"))) for x in (q0, w0)]
    with pytest.raises(ChunkSeen):
        jax.shard_map(body, mesh=mesh, in_specs=(P("b"), P("b")), out_specs=P("b"))(*sharded)
    assert inside == [True] and sizes == [3, 2], (inside, sizes)


def test_an_array_is_split_across_devices_only_on_a_mesh_axis_of_several_devices_outside_shard_map():
    """``split_across_devices`` reads the type: a plain array, one sharded over a mesh axis of one
    device, and a shard inside a ``shard_map`` (its axis manual) are not split. Split arrays (an
    Explicit mesh of four devices: True; an Auto one, whose type does not say: False) are checked
    in ``tests/test_sharding.py``'s subprocess, which has the devices."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxquat._threads import split_across_devices

    mesh = jax.make_mesh((1,), ("b",))
    x = jnp.zeros((4, 3), DTYPE)
    sharded = jax.device_put(x, NamedSharding(mesh, P("b")))
    seen = {}

    def note(name):
        def body(y):
            seen[name] = split_across_devices(y)
            return y

        return body

    jax.jit(note("plain"))(x)
    jax.jit(note("one device"))(sharded)
    jax.jit(jax.shard_map(note("shard_map"), mesh=mesh, in_specs=P("b"), out_specs=P("b")))(sharded)
    assert seen == {"plain": False, "one device": False, "shard_map": False}, seen
    assert jax.typeof(sharded).sharding.spec[0] == "b"  # the sharding is in the type: the check can fail


def test_a_program_compiled_with_the_options_splits_no_loop_and_computes_the_same_bits():
    """The scan path's gradient for 64 bodies (``DTYPE``), compiled with and without the pass: the
    same values to the bit, and with the options no kernel carries XLA's partition of its loop
    (``outer_dimension_partitions``; on a one-core machine XLA partitions nothing either way)."""
    q0, w0 = _bodies(64)

    def loss(w):
        return jnp.sum(_final_attitudes(q0, w) * jnp.arange(4, dtype=w.dtype)[None])

    grad = jax.grad(loss)
    default = jax.jit(grad)
    one_thread = jax.jit(grad, compiler_options=OPTIONS)
    assert "outer_dimension_partitions" not in one_thread.lower(w0).compile().as_text()
    a, b = np.asarray(default(w0)), np.asarray(one_thread(w0))
    assert a.tobytes() == b.tobytes()


def test_simulate_compiles_with_the_options_eagerly_and_stays_nestable(monkeypatch):
    """An eager ``simulate`` on a small float32 batch compiles its own program with the options (a
    second, cached ``jit``; in float64 the default program runs), whose values equal the default
    program's to the bit; inside a caller's ``jit`` whose arguments are all concrete (NumPy
    constants) it is a plain nested ``jit`` (JAX raises ``ValueError`` for compiler options staged
    into another ``jit``) and adds no top-level program."""
    from jaxquat.integration import numerical_solve

    numerical_solve._one_thread_solve.cache_clear()
    q0, w0 = _bodies(8)
    eager = np.asarray(_final_attitudes(q0, w0))
    used = numerical_solve._one_thread_solve.cache_info().currsize
    assert used == (1 if np.dtype(DTYPE).itemsize <= 4 else 0)
    q_np, w_np = np.asarray(q0), np.asarray(w0)
    nested = jax.jit(lambda s: _final_attitudes(q_np, w_np) * s)(jnp.asarray(1, DTYPE))
    np.testing.assert_allclose(np.asarray(nested), eager, rtol=0, atol=16 * np.finfo(DTYPE).eps)
    assert numerical_solve._one_thread_solve.cache_info().currsize == used  # no new top-level program
    monkeypatch.setattr(numerical_solve, "cpu_compiler_options", lambda batch, dtype: {})
    default = np.asarray(_final_attitudes(q0, w0))  # the default program, eagerly
    assert default.tobytes() == eager.tobytes()


def test_the_options_reach_the_compiled_program():
    """``jax.jit``'s ``compiler_options`` with the pass name: the compiled program of a kernel XLA
    would split on a machine with two threads or more (a long element-wise loop) carries no
    partition, and jaxquat's own ``solve`` with the options compiles (``eqx.filter_jit`` passes
    them to ``jax.jit``)."""
    x = jnp.ones(1000, DTYPE)

    def work(x):
        acc = x
        for i in range(150):
            acc = acc * x + 0.01 * i
        return acc

    text = jax.jit(work, compiler_options=OPTIONS).lower(x).compile().as_text()
    assert not re.search(r"outer_dimension_partitions", text)


@pytest.mark.parametrize(
    ("threads", "multiple"), [(1, 1), (2, 2), (3, 12), (4, 4), (6, 24), (8, 8), (12, 48), (16, 16)]
)
def test_the_batch_multiple_is_divided_by_the_threads_and_every_power_of_two_up_to_them(monkeypatch, threads, multiple):
    """XLA splits a kernel into at most as many parts as its pool has threads, and an uneven split
    runs about three times slower (``batch_multiple``'s docstring): the multiple is the least one
    that the thread count and every power of two up to it divide (read from the CPUs this
    process may run on, patched here)."""
    import os

    from jaxquat import _threads

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(threads)), raising=False)
    assert _threads.pool_threads.__wrapped__() == threads
    monkeypatch.setattr(_threads, "pool_threads", lambda: threads)
    m = _threads.batch_multiple.__wrapped__()
    assert m == multiple
    assert m % threads == 0 and all(m % 2**k == 0 for k in range(threads.bit_length()) if 2**k <= threads)
    assert _threads.padded_batch(1, m) == 1  # one body is not a batch
    assert [_threads.padded_batch(n, m) % m for n in (2, m + 1, 3 * m - 1)] == [0, 0, 0]
    assert _threads.padded_batch(m + 1, m) == 2 * m and _threads.padded_batch(2 * m, m) == 2 * m


def test_a_batch_padded_to_the_threads_multiple_gives_the_same_states_and_derivatives(monkeypatch):
    """``simulate`` pads a batch (and on the scan path each chunk) to a multiple of
    ``batch_multiple`` with copies of the first body, and drops their results. Padded to 4
    (``batch_multiple`` patched) against not padded (1): 7 bodies by the closed form and with a
    full tensor per body over a (2, 3) batch (the principal-axes path), and the scan path's
    states, gradient and ``jvp`` (``LieEuler``: the padding does not depend on the tableau, and
    its one stage compiles fastest), whole (7 -> 8) and in chunks (chunks of at most 3 -> 2
    chunks of 4): the scan path's to the bit, the closed form's to rounding, and the solvers did
    see the padded batches (spies). The closed form's reductions over the saved times are
    vectorised across bodies, so another body count sums in another order: its states within 8
    eps of their largest element (measured 1.2 eps in float32, 0 in float64; its gradient, whose
    program compiles for seconds, 8 and 64 eps, is left to the scan path's derivatives through
    the same padding)."""
    from jaxquat import _threads
    from jaxquat.integration import numerical_solve, simulation, struct_of_arrays

    q0, w0 = _bodies(7)
    rng = np.random.default_rng(6)
    axes = np.asarray(jq.to_matrix(jq.normalize(jnp.asarray(rng.normal(size=(2, 3, 4))))), np.float64)
    moments = np.asarray([1.0, 2.0, 2.5]) * rng.uniform(1.0, 2.0, size=(2, 3, 1))  # triangle inequality kept
    tensors = jnp.asarray(np.einsum("...ij,...j,...kj->...ik", axes, moments, axes), DTYPE)
    ts = np.asarray([0.0, 0.05, 0.1], DTYPE)
    diag = I_DIAG.astype(DTYPE)

    def closed(w):
        return jq.simulate(q0, w, diag, ts).q

    def scan(w):
        return jq.simulate(q0, w, diag, ts, solver=jq.LieEuler(), dt0=0.05).q

    def results():
        out = [closed(w0), jq.simulate(q0[:6].reshape(2, 3, 4), w0[:6].reshape(2, 3, 3), tensors, ts).q]
        out += [scan(w0), jax.grad(lambda w: jnp.sum(jnp.sin(scan(w))))(w0)]
        return out + [jax.jvp(scan, (w0,), (jnp.ones_like(w0),))[1]]

    seen = []
    propagate, solve = simulation.propagate, struct_of_arrays.solve
    monkeypatch.setattr(simulation, "propagate", lambda q, *a: seen.append(q[..., 0].size) or propagate(q, *a))
    monkeypatch.setattr(struct_of_arrays, "solve", lambda *a, **k: seen.append(a[3].shape[0]) or solve(*a, **k))
    runs = {}
    for multiple, chunk in [(1, None), (4, None), (1, 3), (4, 3)]:
        monkeypatch.setattr(_threads, "batch_multiple", lambda m=multiple: m)
        if chunk:
            monkeypatch.setattr(numerical_solve, "_CHUNK_BYTES", chunk * np.dtype(DTYPE).itemsize)
        seen.clear()
        runs[multiple, chunk] = results()
        if multiple == 4:
            assert seen and all(n % 4 == 0 for n in seen), (chunk, seen)
        else:  # the batches as given: 7 bodies, the (2, 3) batch's 6, chunks of 3
            assert seen and set(seen) <= {7, 6, 3}, (chunk, seen)
    eps = float(jnp.finfo(DTYPE).eps)
    for chunk in (None, 3):
        for a, b in zip(runs[4, chunk][:2], runs[1, chunk][:2], strict=True):
            assert a.shape == b.shape
            assert float(jnp.max(jnp.abs(a - b))) <= 8 * eps * float(jnp.max(jnp.abs(b))), (chunk, a.shape)
        for a, b in zip(runs[4, chunk][2:], runs[1, chunk][2:], strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_derivatives_take_larger_chunks_where_xla_splits_kernels_between_threads(monkeypatch):
    """The scan path's derivative chunks: ``_DERIVATIVE_CHUNK`` bodies on one thread,
    ``_DERIVATIVE_CHUNK_THREADS`` where XLA's pool has more (at 10^5 float32 bodies on two cores the
    gradient 4.9 -> 3.0 s; the constants' comments), never more than the values' chunks (float64's
    10 000, a torque's 2000); the values' chunks do not change."""
    from jaxquat import _threads
    from jaxquat.integration import numerical_solve as ns

    def chunks(threads, dtype, torque=None):
        monkeypatch.setattr(_threads, "pool_threads", lambda: threads)
        q0 = np.zeros((4,), dtype)  # only its dtype is read
        cfg = ns.configure(jq.RKMK4(), torque, "body", 0.01, 1e-6, 1e-6, None, None, False, TS, 2, q0, True)
        return cfg.chunks[:2]

    f32, f64 = ns._CHUNK_BYTES // 4, ns._CHUNK_BYTES // 8
    assert chunks(1, np.float32) == (f32, ns._DERIVATIVE_CHUNK)
    assert chunks(2, np.float32) == (f32, min(f32, ns._DERIVATIVE_CHUNK_THREADS))
    assert chunks(2, np.float32) != chunks(1, np.float32)
    assert chunks(1, np.float64) == (f64, ns._DERIVATIVE_CHUNK)
    assert chunks(8, np.float64) == (f64, min(f64, ns._DERIVATIVE_CHUNK_THREADS))
    torque = lambda t, q, w, args: -w  # noqa: E731
    assert chunks(2, np.float32, torque) == (ns._TORQUE_CHUNK, ns._TORQUE_CHUNK)
