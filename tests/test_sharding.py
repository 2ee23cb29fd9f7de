"""Batched simulation split across devices with jax.sharding gives the same numbers as the
unsharded run, and stays split. Four host (CPU) devices are forced with XLA_FLAGS, which must be
set before jax starts, so the check runs in a subprocess (once per make test, in the float32
pass)."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest

from frames import script_in_deep_frame
from helpers import X64

ROOT = pathlib.Path(__file__).parent.parent

SCRIPT = r"""
import os
# Added to the worker's XLA_FLAGS (tests/conftest.py's compiler flags, which this process inherits):
# replacing them compiled with XLA's defaults, 71 s for this script against 48 s (float32, one core
# of a 2-core EPYC, session 71).
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
os.environ["JAX_PLATFORMS"] = "cpu"  # host devices, also on a machine with a GPU
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
import jaxquat as jq
assert len(jax.devices()) == 4, jax.devices()


def gap(a, b):
    # On the host, in NumPy: jnp's subtract, abs and max on split arrays compile a program for the
    # mesh at each call (9 such comparisons took 5.9 s of this script's 80 s, one core, session 78).
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))

rng = np.random.default_rng(0)
n = 64
q0 = rng.normal(size=(n, 4)); q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
args = [jnp.asarray(x, jnp.float32) for x in (q0, rng.normal(size=(n, 3)), np.sort(rng.uniform(1, 2, (n, 3)), -1))]
ts = jnp.asarray([0.0, 0.5, 1.0], jnp.float32)

@jax.jit
def run(q0, w0, moments):
    sim = jq.simulate(q0, w0, jax.vmap(jnp.diag)(moments), ts, solver=jq.RKMK4(), dt0=0.01)
    return sim.q, sim.omega

plain = run(*args)
mesh = Mesh(np.array(jax.devices()), ("bodies",))
sharded_args = [jax.device_put(a, NamedSharding(mesh, PartitionSpec("bodies"))) for a in args]
sharded = run(*sharded_args)
assert len(sharded[0].sharding.device_set) == 4, sharded[0].sharding
for a, b in zip(plain, sharded):
    diff = gap(a, b)
    assert diff <= 1e-6, diff
    print("max difference", diff)

# A batch larger than a chunk (simulate's scan path solves chunks one after another): chunks of 8
# bodies here. Each chunk is spread over the devices, so every device works on every chunk; before
# session 68 an Explicit mesh raised a ValueError in lax.map and an Auto mesh ran every body on
# every device (the results replicated, no faster than one device).
from jax.sharding import AxisType
from jaxquat.integration import numerical_solve

def cost(w0, q0, moments):
    q, w = run(q0, w0, moments)
    return jnp.sum(jnp.sin(q[:, -1]) ** 2) + jnp.sum(w[:, -1] * w[:, -1])

whole = (*plain, jax.jit(jax.grad(cost))(args[1], args[0], args[2]))
numerical_solve._CHUNK_BYTES = 8 * 4
run = jax.jit(run.__wrapped__)  # traced again, in chunks
grad = jax.jit(jax.grad(cost))
for kind in (None, AxisType.Auto, AxisType.Explicit):
    if kind is None:
        inputs = args
    else:
        mesh = jax.make_mesh((4,), ("bodies",), axis_types=(kind,))
        inputs = [jax.device_put(a, NamedSharding(mesh, PartitionSpec("bodies"))) for a in args]
    results = (*run(*inputs), grad(inputs[1], inputs[0], inputs[2]))
    for a, b, what in zip(results, whole, ("q", "omega", "grad w0"), strict=True):
        if kind is not None:
            assert len(a.sharding.device_set) == 4 and not a.sharding.is_fully_replicated, (kind, what, a.sharding)
        diff = gap(a, b)
        assert diff <= 1e-6, (kind, what, diff)
        print("in chunks", kind, what, "max difference", diff)

# On the Explicit mesh (the loop's last) the types say that the batch is split, so the step's
# exponentials choose their branch element by element: a batch-wide choice is a cross-device
# all-reduce at every step (three of them in this gradient's program before session 70; 10^5
# bodies x 1000 RKMK4 steps on 2 CPU devices, the gradient 5.9 against 2.5 s).
hlo = grad.lower(inputs[1], inputs[0], inputs[2]).compile().as_text()
print("all-reduce in the Explicit gradient:", hlo.count("all-reduce("))
from jaxquat._threads import split_across_devices
split = {}
for kind in (AxisType.Auto, AxisType.Explicit):
    mesh = jax.make_mesh((4,), ("bodies",), axis_types=(kind,))
    x = jax.device_put(args[0], NamedSharding(mesh, PartitionSpec("bodies")))
    jax.jit(lambda x, kind=kind: split.setdefault(str(kind), split_across_devices(x)) and x)(x)
print("split across devices:", split)

# JAX's explicit sharding fails inside the closed form (a reshape of a sharded axis) and inside
# diffeqsolve's paths (diffrax's term check, its loop under vmap). On an Explicit mesh simulate runs
# the closed form and the adaptive path in a shard_map of their own (the unsharded run's values; the
# result stays split; the closed form's gradient under jit below); an Auto mesh runs both. The
# fixed-step diffeqsolve path (an adjoint given) refuses the split batch, with the ways out.
inertia = np.diag([1.0, 2.0, 2.5]).astype(np.float32)


# its args: arrays (replicated to every device; an integer one too) and leaves that are not arrays
def damping(t, q, w, a):
    return -a["k"] * w * (2.0 if a["mode"] == "double" else 1.0) * a["scale"] * a["n"]


# rtol = atol = 1e-5, not simulate's 1e-8 (below float32's resolution: the controller took many
# more steps than float32 can use): the split and the plain runs take the same steps either way,
# and the script took 51.4 -> 40.8 s (the split gradient, which solves the whole batch on each of
# the 4 devices in its backward pass, 14.9 -> 9.4 s; one core of a 2-core Xeon, session 90).
damped = {
    "solver": jq.RKMK45(),
    "rtol": 1e-5,
    "atol": 1e-5,
    "torque": damping,
    "args": {"k": jnp.float32(0.3), "n": jnp.int32(1), "mode": "double", "scale": 0.5},
}
for label, kw in (("closed form", {}), ("adaptive", damped)):
    plain_q = jq.simulate(args[0], args[1], inertia, ts, **kw).q
    for kind in (AxisType.Auto, AxisType.Explicit):
        mesh = jax.make_mesh((4,), ("bodies",), axis_types=(kind,))
        q, w = (jax.device_put(a, NamedSharding(mesh, PartitionSpec("bodies"))) for a in args[:2])
        got = jq.simulate(q, w, inertia, ts, **kw).q
        diff = gap(got, plain_q)
        assert diff <= 1e-6, (label, kind, diff)
        assert len(got.sharding.device_set) == 4 and not got.sharding.is_fully_replicated, (label, kind, got.sharding)
        print("ran", label, kind)
# Reverse mode through the adaptive path on the Explicit mesh (a custom_vjp whose backward pass is
# the whole batch's vjp on every device; transposing the shard_map failed in diffrax's adjoint):
# the unsharded run's gradients in the initial rates, a gain in the torque's args and the shared
# inertia, the rates' gradient still split. Forward mode is refused with the ways out (0.2 s).
# Solved by diffrax's Heun, adaptive too (the path does not depend on the solver): with RKMK45
# the two gradient programs took 30 s of this script instead of 15 s (one core, 2-core Xeon).
import diffrax


def adaptive_cost(w, k, inertia, q):
    sim = jq.simulate(q, w, inertia, ts, **dict(damped, solver=diffrax.Heun(), args={**damped["args"], "k": k}))
    return jnp.sum(jnp.sin(sim.q[:, -1]) ** 2) + jnp.sum(sim.omega**2)


adaptive_grad = jax.jit(jax.grad(adaptive_cost, (0, 1, 2)))
k, inertia_array = damped["args"]["k"], jnp.asarray(inertia)
g_plain = adaptive_grad(args[1], k, inertia_array, args[0])
g_split = adaptive_grad(w, k, inertia_array, q)
for a, b, what in zip(g_split, g_plain, ("w0", "gain", "inertia"), strict=True):
    diff = gap(a, b)
    assert diff <= 1e-5 * float(np.max(np.abs(b))), (what, diff)
    print("adaptive gradient on the Explicit mesh", what, "difference", diff)
assert len(g_split[0].sharding.device_set) == 4 and not g_split[0].sharding.is_fully_replicated, g_split[0].sharding
try:
    jax.jvp(lambda w: jq.simulate(q, w, inertia, ts, **damped).q, (w,), (w,))
except TypeError as err:
    assert "not available (reverse mode is)" in str(err), err
    print("refused adaptive forward mode")
try:
    jq.simulate(q, w, inertia, ts, solver=jq.RKMK4(), dt0=0.1, adjoint=diffrax.RecursiveCheckpointAdjoint())
except ValueError as err:
    assert "jax.shard_map" in str(err) and "'q0'" in str(err), err
    print("refused fixed-step adjoint")

def closed_form_cost(w, q):
    return jnp.sum(jq.simulate(q, w, inertia, ts).q ** 3)

g_plain = jax.jit(jax.grad(closed_form_cost))(args[1], args[0])
g_split = jax.jit(jax.grad(closed_form_cost))(w, q)  # the Explicit mesh's, the loop's last
diff = gap(g_split, g_plain)
assert diff <= 1e-5 * float(np.max(np.abs(g_plain))), diff
print("closed form gradient on the Explicit mesh, difference", diff)
"""


@pytest.mark.skipif(X64, reason="runs once per make test, in the float32 pass (the issue's batch dtype)")
def test_sharded_batch_matches_unsharded():
    # From a deep frame, as the suite's tests run (tests/frames.py: 256 000 page faults against 501 000).
    script = script_in_deep_frame(SCRIPT)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("max difference") == 11, out.stdout
    assert "all-reduce in the Explicit gradient: 0" in out.stdout, out.stdout
    assert "split across devices: {'AxisType.Auto': False, 'AxisType.Explicit': True}" in out.stdout, out.stdout
    for label in ("closed form", "adaptive"):
        for kind in ("AxisType.Auto", "AxisType.Explicit"):
            assert f"ran {label} {kind}" in out.stdout, out.stdout
    for line in (
        "adaptive gradient on the Explicit mesh w0",
        "adaptive gradient on the Explicit mesh gain",
        "adaptive gradient on the Explicit mesh inertia",
        "refused adaptive forward mode",
        "refused fixed-step adjoint",
        "closed form gradient on",
    ):
        assert line in out.stdout, out.stdout


def test_forward_mode_on_a_split_adaptive_batch_is_refused_with_the_ways_out(monkeypatch):
    """Forward mode through the adaptive path on a batch split by an Explicit mesh meets the
    ``custom_vjp`` of its sharded solve, which JAX refuses with a ``TypeError`` naming
    ``custom_vjp`` (eagerly, when the solve's program is lowered); ``simulate`` raises it again
    with the ways out (the subprocess above meets the real one), and any other ``TypeError`` as it
    is. Here, in every dtype pass, the split batch and JAX's error are stood in for."""
    import jax.numpy as jnp
    import numpy as np

    import jaxquat as jq
    from jaxquat.integration import simulation

    def refusal(message):
        def raising(*args, **kwargs):
            raise TypeError(message)

        return raising

    monkeypatch.setattr(simulation, "_split_argument", lambda q0, omega0, path: 0)
    state = (jq.identity((2,)), jnp.ones((2, 3)), np.eye(3), np.linspace(0.0, 1.0, 3))
    monkeypatch.setattr(
        simulation, "_numerical_in_shards", refusal("can't apply forward-mode autodiff (jvp) to a custom_vjp function.")
    )
    with pytest.raises(TypeError, match=r"not available \(reverse mode is\): take the scan path"):
        jq.simulate(*state, torque=lambda t, q, w, a: -w)
    monkeypatch.setattr(simulation, "_numerical_in_shards", refusal("another"))
    with pytest.raises(TypeError, match="^another$"):
        jq.simulate(*state, torque=lambda t, q, w, a: -w)


def test_simulate_in_a_shard_map_body_takes_a_numpy_inertia_and_matches_the_plain_run(monkeypatch):
    """``simulate`` as the body of a ``jax.shard_map`` (a mesh of this process's first device, whose
    axis is manual all the same): a NumPy inertia is validated there (before session 69 the
    check's ``jnp.asarray`` returned a ``ShardMapTracer`` and ``simulate`` raised ``TypeError``),
    and the closed form, the scan path in chunks (``_SHARD_MAP_CHUNK`` set to 3 bodies of 8) and
    ``diffeqsolve``'s path (an adjoint given; the scan's steps) give the plain run's values.
    ``diffeqsolve`` needs ``check_vma=False``: diffrax's loop carries a flag that JAX's check of
    varying axes refuses (diffrax issue #735)."""
    import diffrax
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    import jaxquat as jq
    from helpers import DTYPE, assert_close
    from jaxquat.integration import numerical_solve

    monkeypatch.setattr(numerical_solve, "_SHARD_MAP_CHUNK", 3)
    rng = np.random.default_rng(2)
    q0 = jq.normalize(jnp.asarray(rng.normal(size=(8, 4)), DTYPE))
    w0 = jnp.asarray(rng.normal(size=(8, 3)), DTYPE)
    inertia = np.diag([1.0, 2.0, 2.5]).astype(DTYPE)
    ts = np.linspace(0.0, 0.2, 3).astype(DTYPE)
    mesh = jax.make_mesh((1,), ("b",), devices=jax.devices()[:1])
    sharded = [jax.device_put(x, NamedSharding(mesh, P("b"))) for x in (q0, w0)]
    scan = dict(solver=jq.LieEuler(), dt0=0.05)
    cases = {
        "closed form": ({}, {}),
        "scan": (scan, scan),
        "diffeqsolve": (dict(scan, adjoint=diffrax.RecursiveCheckpointAdjoint()), scan),  # same steps
    }
    for what, (kw, plain_kw) in cases.items():
        plain = jq.simulate(q0, w0, inertia, ts, **plain_kw)

        def body(q, w, kw=kw):
            sim = jq.simulate(q, w, inertia, ts, **kw)
            return sim.q, sim.omega

        specs = dict(in_specs=(P("b"), P("b")), out_specs=P("b"), check_vma=what != "diffeqsolve")
        run = jax.shard_map(body, mesh=mesh, **specs)
        for a, b in zip(run(*sharded), (plain.q, plain.omega), strict=True):
            assert_close(a, b, tol=1e-12 if X64 else 1e-6, what=what)
