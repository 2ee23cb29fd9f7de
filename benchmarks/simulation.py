"""Simulation throughput at known accuracy, gradient cost and compile time.

Torque-free asymmetric bodies (principal moments (1, 2, 3), random attitudes, rates
~ N(0, 1)), float32, dt = 0.01, 1000 steps, batches of 1, 10^3 and 10^5. Contenders,
all jitted and timed after compilation with block_until_ready (the least of up to ``--repeats``
calls within 3 s; the autodiff table: the least of interleaved rounds, ``_autodiff_times``):

- jaxquat.simulate with RKMK4 (the Lie-group solver, through diffrax);
- jaxquat.RKMK4 as a user's diffrax solver: diffrax.diffeqsolve on ODETerm(jaxquat.RigidBody);
- a hand-written classic RK4 on the raw 7-state ODE, renormalising q each step,
  lax.scan + vmap-free batching (the fastest thing a user could write by hand);
- diffrax Tsit5 on the raw 7-state ODE at the same fixed step;
- MuJoCo MJX (mujoco-mjx, if importable): one free body, no gravity, no contacts,
  its RK4 integrator, vmapped over the batch (batch <= 10^3: it is slow). It runs in
  float64 (MJX builds its model in float64 when x64 is on, as it is here for the
  reference), so its row is not float32.

Beside each throughput: the largest attitude error at T = 10 against the exact
solution (jaxquat.euler_poinsot in float64) and the largest | |q| - 1 |.
Also: the cost of autodiff against the forward pass (reverse mode: jax.grad of a
final-attitude loss; forward mode: one jvp tangent, and jacfwd with 3 columns), float32 and
float64, at batches 10^3 and 10^5, for simulate (RKMK4, and the default closed form) and the
hand RK4 (checkpointed as simulate's scan path is), and at 10^3 for the minimum-time solver's
held-torque rollout (80 intervals x 4 RKMK4 steps, vmapped over the bodies), compile time (time to the first result
of simulate, and of one optax step through it), and import time (import jaxquat, its first
rotation function, its first simulate). And XLA's split of each CPU kernel between threads at
small batches: the scan path and the hand RK4 compiled with XLA's defaults and with the split
off (``jq.cpu_compiler_options``' option), their calls interleaved.

    python benchmarks/simulation.py [--batches 1 1000 100000] [--grad-batches 1000 100000]
                                    [--write docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import textwrap
import time

import jax

jax.config.update("jax_enable_x64", True)  # the float64 reference; every contender runs float32

import diffrax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import jaxquat as jq  # noqa: E402
from jaxquat._threads import ONE_THREAD  # noqa: E402  # the option, also where cpu_compiler_options skips it
from jaxquat.control.transcription import held_torque_states  # noqa: E402  # the solver's rollout, private
from _report import least_time, machine, write_section  # noqa: E402

DT, STEPS = 0.01, 1000
MOMENTS = np.array([1.0, 2.0, 3.0])
F32 = jnp.float32


def bodies(n, seed=0):
    rng = np.random.default_rng(seed)
    q0 = rng.normal(size=(n, 4))
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    return q0, rng.normal(size=(n, 3))


def raw_field(y):
    """The 7-state ODE: q' = 1/2 q (0, w), w' = I^-1 (I w x w) for principal moments."""
    q, w = y[..., :4], y[..., 4:]
    m = jnp.asarray(MOMENTS, y.dtype)
    qd = 0.5 * jnp.stack(
        [
            -q[..., 1] * w[..., 0] - q[..., 2] * w[..., 1] - q[..., 3] * w[..., 2],
            q[..., 0] * w[..., 0] + q[..., 2] * w[..., 2] - q[..., 3] * w[..., 1],
            q[..., 0] * w[..., 1] + q[..., 3] * w[..., 0] - q[..., 1] * w[..., 2],
            q[..., 0] * w[..., 2] + q[..., 1] * w[..., 1] - q[..., 2] * w[..., 0],
        ],
        -1,
    )
    return jnp.concatenate([qd, jnp.cross(m * w, w) / m], -1)


def hand_rk4(q0, w0, checkpoint=False):
    def step(y, _):
        k1 = raw_field(y)
        k2 = raw_field(y + 0.5 * DT * k1)
        k3 = raw_field(y + 0.5 * DT * k2)
        k4 = raw_field(y + DT * k3)
        y = y + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        q = y[..., :4] / jnp.linalg.norm(y[..., :4], axis=-1, keepdims=True)
        return jnp.concatenate([q, y[..., 4:]], -1), None

    y, _ = jax.lax.scan(jax.checkpoint(step) if checkpoint else step, jnp.concatenate([q0, w0], -1), None, length=STEPS)
    return y[..., :4]


def hand_rk4_checkpointed(q0, w0):
    """The hand RK4 with each step rematerialised in reverse mode (as simulate's scan path): without
    it the gradient at 10^5 bodies stores every step's residuals (52 GB, out of memory here)."""
    return hand_rk4(q0, w0, checkpoint=True)


def jaxquat_diffeqsolve(q0, w0):
    """``jq.RKMK4`` handed to ``diffrax.diffeqsolve`` on ``ODETerm(jq.RigidBody)``, a batch as
    ``(q (n, 4), w (n, 3))``: the Lie solver as a diffrax user meets it. The times in the state's
    dtype (diffrax promotes the state to the times' dtype, float64 under this script's x64)."""
    inertia = jnp.diag(jnp.asarray(MOMENTS, q0.dtype))
    t0, t1, dt0 = (jnp.asarray(x, q0.dtype) for x in (0.0, STEPS * DT, DT))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(jq.RigidBody(inertia)),
        jq.RKMK4(),
        t0,
        t1,
        dt0,
        (q0, w0),
        saveat=diffrax.SaveAt(t1=True),
        max_steps=STEPS + 4,
    )
    return sol.ys[0][0]


def tsit5(q0, w0):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, a: raw_field(y)),
        diffrax.Tsit5(),
        0.0,
        STEPS * DT,
        DT,
        jnp.concatenate([q0, w0], -1),
        saveat=diffrax.SaveAt(t1=True),
        max_steps=STEPS + 4,
    )
    return sol.ys[0, ..., :4]


def jaxquat_rkmk4(q0, w0, torque=None, args=None):
    ts = np.asarray([0.0, STEPS * DT], q0.dtype)  # numpy: concrete under jit, so simulate can plan its steps
    inertia = jnp.diag(jnp.asarray(MOMENTS, q0.dtype))
    return jq.simulate(q0, w0, inertia, ts, torque=torque, args=args, solver=jq.RKMK4(), dt0=DT, max_steps=STEPS + 4).q[
        ..., -1, :
    ]


PD_GAINS = (0.5, 0.8)


def _pd_torque(t, q, w, gains):
    """A PD law towards the identity, ``-k_p sign(q_w) q_v - k_d w``, its gains in ``args``: the
    element-wise kind of torque whose gradient stalled under XLA's default CPU emitters until
    session 24 (``docs/integrators.md``)."""
    return -gains[0] * jnp.where(q[0] < 0, -1.0, 1.0) * q[1:] - gains[1] * w


def jaxquat_rkmk4_pd(q0, w0):
    """:func:`jaxquat_rkmk4` with :func:`_pd_torque` acting."""
    return jaxquat_rkmk4(q0, w0, _pd_torque, jnp.asarray(PD_GAINS, q0.dtype))


def jaxquat_closed_form(q0, w0):
    """``simulate``'s default torque-free path (no ``solver``: :func:`jaxquat.euler_poinsot`) at the
    same final time, the inertia a NumPy array as a user writes it (concrete, so known diagonal)."""
    ts = np.asarray([0.0, STEPS * DT], q0.dtype)
    return jq.simulate(q0, w0, np.diag(np.asarray(MOMENTS, q0.dtype)), ts).q[..., -1, :]


ROLLOUT_INTERVALS, ROLLOUT_SUBSTEPS = 80, 4


def held_torque_rollout(q0, w0):
    """The final attitude of ``minimum_time_reorientation``'s held-torque rollout (RKMK4 in rows
    through a torque held on 80 intervals, 4 steps each, over the same 10 time units), each body
    on its own under ``jax.vmap``, as the single-shooting solver integrates one problem: issue 17's
    third place for the gradient's 3x (session 30's table in docs/benchmarks.md)."""
    k = jnp.arange(ROLLOUT_INTERVALS, dtype=q0.dtype)
    u = 0.05 * jnp.stack([jnp.sin(0.1 * k), jnp.cos(0.07 * k), jnp.sin(0.05 * k + 1.0)], axis=-1)
    inertia = jnp.diag(jnp.asarray(MOMENTS, q0.dtype))
    T = jnp.asarray(STEPS * DT, q0.dtype)

    def one(q, w):
        return held_torque_states(inertia, q, w, T, u, ROLLOUT_SUBSTEPS)[0][-1]

    return jax.vmap(one)(q0, w0)


def mjx_contender():
    """MJX free body with the same moments (None if mujoco-mjx is not installed)."""
    try:
        import mujoco
        from mujoco import mjx
    except ImportError:
        return None
    xml = f"""<mujoco><option gravity="0 0 0" integrator="RK4" timestep="{DT}"/>
      <worldbody><body><freejoint/><inertial pos="0 0 0" mass="1" diaginertia="{MOMENTS[0]} {MOMENTS[1]} {MOMENTS[2]}"/>
      </body></worldbody></mujoco>"""
    model = mjx.put_model(mujoco.MjModel.from_xml_string(xml))
    data0 = mjx.make_data(model)

    def run(q0, w0):
        def one(q, w):
            dt = data0.qpos.dtype  # the model's (float64 here, as x64 is on for the reference)
            d = data0.replace(
                qpos=jnp.concatenate([jnp.zeros(3, dt), q.astype(dt)]),
                qvel=jnp.concatenate([jnp.zeros(3, dt), w.astype(dt)]),
            )  # free-joint rates: body frame
            d, _ = jax.lax.scan(lambda d, _: (mjx.step(model, d), None), d, None, length=STEPS)
            return d.qpos[3:7]

        return jax.vmap(one)(q0, w0)

    return run


def accuracy(q, q0, w0):
    exact, _ = jq.euler_poinsot(jnp.asarray(q0), jnp.asarray(w0), jnp.asarray(MOMENTS), jnp.asarray(STEPS * DT))
    q = jnp.asarray(q, jnp.float64)
    err = jq.angle_between(q / jnp.linalg.norm(q, axis=-1, keepdims=True), exact)
    return float(jnp.max(err)), float(jnp.median(err)), float(jnp.max(jnp.abs(jnp.linalg.norm(q, axis=-1) - 1)))


def throughput(batches, repeats):
    contenders = {
        "jaxquat simulate, RKMK4": jaxquat_rkmk4,
        "jaxquat RKMK4 in diffeqsolve": jaxquat_diffeqsolve,
        "hand-written RK4 (raw ODE)": hand_rk4,
        "diffrax Tsit5 (raw ODE)": tsit5,
    }
    mjx_run = mjx_contender()
    if mjx_run is not None:
        contenders["MuJoCo MJX, RK4"] = mjx_run
    rows = []
    for n in batches:
        q0, w0 = bodies(n)
        args = (jnp.asarray(q0, F32), jnp.asarray(w0, F32))
        for name, fn in contenders.items():
            if name.startswith("MuJoCo") and n > 1000:
                rows.append((n, name, None, None, None, None))
                continue
            f = jax.jit(fn)
            wall = least_time(f, *args, repeats=repeats)
            err, med, drift = accuracy(f(*args), q0, w0)
            rows.append((n, name, n * STEPS / wall, err, med, drift))
            print(
                f"batch {n:>6} {name:<28} {n * STEPS / wall:.3e} body-steps/s  error max {err:.1e} median {med:.1e} rad"
                f"  | |q|-1 | {drift:.1e}",
                flush=True,
            )
    return rows


def gradient_table(batches, repeats):
    """Forward pass, reverse mode (``jax.grad`` of a final-attitude loss), forward mode (one
    ``jax.jvp`` tangent on ``w0``, and ``jax.jacfwd`` with 3 columns: a rate offset shared by
    the batch) for jaxquat's RKMK4 (torque-free, and with a PD torque law), the default closed
    form and the hand RK4 (torque-free), and up to 10^4 bodies the minimum-time solver's held-torque
    rollout, float32 and float64: ``(dtype, batch, contender, forward, reverse, jvp, jacfwd)`` in seconds."""
    rows = []
    for dtype in (F32, jnp.float64):
        for n in batches:
            q0, w0 = bodies(n, seed=1)
            q0, w0 = jnp.asarray(q0, dtype), jnp.asarray(w0, dtype)
            target = jq.random(jax.random.PRNGKey(0), (n,), dtype)
            warm = 1 if n > 10_000 else 2
            for name, run in (
                ("jaxquat simulate, RKMK4", jaxquat_rkmk4),
                ("jaxquat simulate, RKMK4, PD torque", jaxquat_rkmk4_pd),
                ("jaxquat simulate, closed form (default)", jaxquat_closed_form),
                ("hand-written RK4, checkpointed", hand_rk4_checkpointed),
                *(() if n > 10_000 else (("minimum-time held-torque rollout, 80 x 4 steps", held_torque_rollout),)),
            ):
                fwd, rev, jvp, jac = _autodiff_times(run, q0, w0, target, repeats, warm)
                rows.append((jnp.dtype(dtype).name, n, name, fwd, rev, jvp, jac))
                print(
                    f"{jnp.dtype(dtype).name} batch {n:>7} {name:<40} forward {fwd * 1e3:8.2f} ms"
                    f"  grad {rev / fwd:5.2f}x  jvp {jvp / fwd:5.2f}x  jacfwd(3) {jac / fwd:5.2f}x",
                    flush=True,
                )
    return rows


def thread_table(repeats):
    """XLA's split of each CPU kernel between threads, on and off (``ONE_THREAD``), for the scan
    path and the hand RK4 at small batches: ``(dtype, batch, contender, case, split, one thread,
    picked)``, seconds, the two programs' calls interleaved (median of ``3 * repeats`` each), and
    whether :func:`jaxquat.cpu_compiler_options` picks the option for that batch and dtype."""
    rows = []
    for dtype, n in ((F32, 250), (F32, 1000), (F32, 4000), (jnp.float64, 1000)):
        q0, w0 = bodies(n, seed=1)
        q0, w0 = jnp.asarray(q0, dtype), jnp.asarray(w0, dtype)
        target = jq.random(jax.random.PRNGKey(0), (n,), dtype)
        contenders = (("jaxquat simulate, RKMK4", jaxquat_rkmk4), ("hand RK4, checkpointed", hand_rk4_checkpointed))
        for name, run in contenders:
            for case, (fn, args) in zip(("forward", "grad", "jvp"), _autodiff_cases(run, q0, w0, target)):
                split, one = _interleaved((jax.jit(fn), jax.jit(fn, compiler_options=ONE_THREAD)), args, 3 * repeats)
                rows.append((jnp.dtype(dtype).name, n, name, case, split, one, bool(jq.cpu_compiler_options(n, dtype))))
                print(
                    f"{rows[-1][0]} batch {n:>5} {name:<24} {case:<8} split {split * 1e3:8.2f} ms  one thread "
                    f"{one * 1e3:8.2f} ms",
                    flush=True,
                )
    return rows


def _interleaved(fns, args, repeats):
    """Median seconds of each of ``fns(*args)``, their calls alternated after one call each."""
    return _rounds([(f, args) for f in fns], repeats, warm=1, statistic=lambda ts: float(np.median(ts)))


def _rounds(cases, repeats, warm, budget=float("inf"), statistic=min):
    """``statistic`` of each case's seconds: each ``(fn, args)`` of ``cases`` called ``warm`` times,
    then timed in rounds, one call of each case per round. Rounds stop after ``repeats``, or once
    ``budget`` seconds have been spent timing and at least two rounds are done."""
    for fn, a in cases:
        for _ in range(warm):
            jax.block_until_ready(fn(*a))
    times = [[] for _ in cases]
    spent = 0.0
    while len(times[0]) < repeats and (len(times[0]) < 2 or spent < budget):
        for (fn, a), ts in zip(cases, times):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*a))
            ts.append(time.perf_counter() - t0)
            spent += ts[-1]
    return [statistic(ts) for ts in times]


def _autodiff_cases(run, q0, w0, target):
    """``(function, arguments)`` of ``run``'s forward pass, the ``grad`` of a final-attitude loss in
    ``w0``, one ``jvp`` tangent on ``w0`` and a 3-column ``jacfwd`` (a rate offset shared by the batch)."""

    def loss(w):
        return jnp.mean(jnp.sum((run(q0, w) - target) ** 2, -1))

    return (
        (run, (q0, w0)),
        (jax.grad(loss), (w0,)),
        (lambda w, d: jax.jvp(lambda x: run(q0, x), (w,), (d,))[1], (w0, w0)),
        (jax.jacfwd(lambda p: run(q0, w0 + p)), (jnp.zeros(3, w0.dtype),)),
    )


def _autodiff_times(run, q0, w0, target, repeats, warm, budget=20.0):
    """Seconds of ``run``'s forward pass, ``grad``, one-tangent ``jvp`` and 3-column ``jacfwd``:
    each compiled and called ``warm`` times, then timed in rounds, one call of each case per round,
    and the least of each case's samples kept. Rounds stop after ``repeats``, or once ``budget``
    seconds have been spent timing and at least two rounds are done.

    Why rounds and the least: on a 2-core VM a program's calls ran about 2x slower for seconds at a
    time (10^5 float32 bodies x 1000 RKMK4 steps, the forward pass 370-400 ms in most calls and
    780-990 ms in runs of two or three), the same compiled program in one process, with no steal
    time in ``/proc/stat``; pinned to one core the calls did not vary so. Until session 84 each case took the median of
    its own samples, about 3 s of them (two at 10^5 bodies for the gradient), and a slow spell that
    fell on one case's samples set its figure: session 83's table read the scan path's 10^5-body
    float32 ``jvp`` at 1679 ms (4.73x) where the same program took 720-760 ms in processes of its
    own, and a rerun of the table alone read it at 1586 ms.

    Each program is compiled with :func:`jaxquat.cpu_compiler_options` for its batch and dtype, as
    the library's docs tell a user to ``jit`` a loss (one thread for a float32 batch of up to 1024
    on the CPU, XLA's defaults otherwise). Until session 90 they were compiled with XLA's defaults,
    whose split of each kernel between two threads slowed the float32 forward pass at 1000 bodies
    more than its derivatives (2-core Intel Xeon, session 90, defaults -> these options: forward
    24.0 -> 7.0 ms, gradient 52.5 -> 32.5 ms, so the gradient's ratio 2.19x -> 4.65x)."""
    options = jq.cpu_compiler_options(math.prod(q0.shape[:-1]), q0.dtype) or None
    cases = _autodiff_cases(run, q0, w0, target)
    return _rounds([(jax.jit(fn, compiler_options=options), a) for fn, a in cases], repeats, warm, budget)


def compile_times():
    """Time to the first result at batch 1000, float32: ``simulate``, and one optax Adam step through it."""
    q0, w0 = bodies(1000, seed=1)
    q0, w0 = jnp.asarray(q0, F32), jnp.asarray(w0, F32)
    target = jq.random(jax.random.PRNGKey(0), (1000,), F32)

    def loss(w0_):
        q = jaxquat_rkmk4(q0, w0_)
        return jnp.mean(jnp.sum((q - target) ** 2, -1))

    t0 = time.perf_counter()
    jax.block_until_ready(jax.jit(lambda a, b: jaxquat_rkmk4(a, b) + 0)(q0, w0))  # a fresh function: compiles
    first_sim = time.perf_counter() - t0
    opt = optax.adam(1e-2)

    def opt_step(w, state):
        g = jax.grad(loss)(w)
        updates, state = opt.update(g, state, w)
        return optax.apply_updates(w, updates), state

    t0 = time.perf_counter()
    jax.block_until_ready(jax.jit(opt_step)(w0, opt.init(w0)))
    first_step = time.perf_counter() - t0
    return first_sim, first_step


def first_closed_form(repeats=3):
    """Time to the first result of ``simulate``'s default torque-free path (no ``solver``: the closed
    form, :func:`jaxquat.euler_poinsot` at every saved time) as a user meets it: a fresh
    interpreter, an eager call on 1000 bodies and 101 saved times in float32 (least of
    ``repeats`` processes), with how much of it XLA's compilation took; then, in the same
    interpreter, the first optax Adam step through it (a jitted step whose loss is the final
    attitude's squared distance to a target, as :func:`compile_times`' step through the scan path),
    and XLA's share of that."""
    code = textwrap.dedent(
        f"""
        import time, jax, jax.numpy as jnp, numpy as np, jaxquat as jq
        spent = []
        jax.monitoring.register_event_duration_secs_listener(
            lambda name, secs, **kw: spent.append(secs) if name.endswith("backend_compile_duration") else None
        )
        rng = np.random.default_rng(1)
        q0 = jq.normalize(jnp.asarray(rng.normal(size=(1000, 4)), jnp.float32))
        w0 = jnp.asarray(rng.normal(size=(1000, 3)), jnp.float32)
        inertia = jnp.diag(jnp.asarray({list(MOMENTS)}, jnp.float32))
        ts = np.linspace(0.0, 10.0, 101)
        jax.block_until_ready((q0, w0, inertia))
        spent.clear()
        t0 = time.perf_counter()
        jax.block_until_ready(jq.simulate(q0, w0, inertia, ts).q)
        first = (time.perf_counter() - t0, sum(spent))

        import optax
        target = jq.random(jax.random.PRNGKey(0), (1000,), jnp.float32)
        opt = optax.adam(1e-2)
        state = opt.init(w0)
        jax.block_until_ready((target, state))

        def loss(w):
            return jnp.mean(jnp.sum((jq.simulate(q0, w, inertia, ts).q[:, -1] - target) ** 2, -1))

        @jax.jit
        def opt_step(w, state):
            updates, state = opt.update(jax.grad(loss)(w), state, w)
            return optax.apply_updates(w, updates), state

        spent.clear()
        t0 = time.perf_counter()
        jax.block_until_ready(opt_step(w0, state))
        print(*first, time.perf_counter() - t0, sum(spent))
        """
    )
    runs = _fresh_runs(code, repeats)
    return runs[np.argmin(runs[:, 0])]


def import_times(repeats=5):
    """What ``import jaxquat`` adds to ``import jax`` (fresh interpreters, least of ``repeats``), and
    the first use of a rotation (``jq.multiply``: jaxtyping and the rotation modules) and of a
    solver (``jq.RKMK4``: diffrax, equinox, optimistix; ``jaxquat/__init__.pyi``'s names load
    lazily, and ``simulate`` imports them on its first numerical solve only)."""
    code = (
        "import time; t0 = time.perf_counter(); import jax, jax.numpy; t1 = time.perf_counter(); "
        "import jaxquat as jq; t2 = time.perf_counter(); jq.multiply; t3 = time.perf_counter(); "
        "jq.RKMK4; t4 = time.perf_counter(); print(t1 - t0, t2 - t1, t3 - t2, t4 - t3)"
    )
    return np.min(_fresh_runs(code, repeats), axis=0)


def _fresh_runs(code: str, repeats: int) -> np.ndarray:
    """The numbers ``code`` prints, one row per fresh interpreter (``repeats`` of them).

    The interpreters may write and read Python's bytecode cache whatever the caller's environment
    says, as under ``make`` (whose ``unexport PYTHONDONTWRITEBYTECODE`` the Makefile explains): run
    directly with ``PYTHONDONTWRITEBYTECODE=1``, as this machine exports it, each fresh process
    compiled jax and jaxquat from source, and session 86's run read ``import jax`` 1.90 s against
    0.72 s the day before (and 1.27-1.32 s in that hour with the cache)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    runs = [
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env).stdout.split()
        for _ in range(repeats)
    ]
    return np.asarray(runs, float)


def markdown(rows, grad_rows, compiled, imported, closed_form, thread_rows=()):
    first_sim, first_step = compiled
    by = {(n, name): rate for n, name, rate, *_ in rows}
    lines = [
        f"Torque-free bodies (the autodiff table also has a PD torque law), moments (1, 2, 3), float32, dt = {DT}, "
        f"{STEPS} steps; {machine()}. "
        "Error: attitude error at T = 10 against `euler_poinsot` (float64), largest and median over the batch.",
        "",
        "| batch | contender | body-steps/s | vs hand RK4 | final error, max (rad) | median (rad) | max "
        "abs(abs(q) - 1) |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for n, name, rate, err, med, drift in rows:
        if rate is None:
            lines.append(f"| {n:,} | {name} | not run (too slow at this batch) | | | | |")
            continue
        hand = by[(n, "hand-written RK4 (raw ODE)")]
        lines.append(f"| {n:,} | {name} | {rate:.2e} | {rate / hand:.2f}x | {err:.1e} | {med:.1e} | {drift:.1e} |")
    lines += [
        "",
        "Autodiff cost against the forward pass (final-attitude loss; forward mode: one `jax.jvp` "
        "tangent on `w0`, `jax.jacfwd` with 3 columns, a rate offset shared by the batch; each the least of "
        "up to 5 rounds that call the four programs in turn; every program compiled with "
        "`jq.cpu_compiler_options(batch, dtype)`, which turns XLA's split of kernels between threads off for "
        "a float32 batch of up to 1024):",
        "",
        "| dtype | batch | contender | forward | reverse (`grad`) | `jvp` | `jacfwd`, 3 columns |",
        "|---|---:|---|---:|---:|---:|---:|",
    ]
    for dtype, n, name, fwd, rev, jvp, jac in grad_rows:
        lines.append(
            f"| {dtype} | {n:,} | {name} | {fwd * 1e3:.1f} ms | {rev / fwd:.2f}x | {jvp / fwd:.2f}x "
            f"| {jac / fwd:.2f}x |"
        )
    if thread_rows:
        lines += [
            "",
            "XLA's split of each CPU kernel between threads (its pass `cpu-parallel-task-assigner`) at small "
            "batches: the same programs compiled with XLA's defaults and with the split off "
            "(`compiler_options=jq.cpu_compiler_options(batch, dtype)`, which picks it where the last column says), "
            "their calls interleaved, medians:",
            "",
            "| dtype | batch | contender | | XLA's split | one thread | split / one thread | picked |",
            "|---|---:|---|---|---:|---:|---:|---|",
        ]
        for dtype, n, name, case, split, one, picked in thread_rows:
            lines.append(
                f"| {dtype} | {n:,} | {name} | {case} | {split * 1e3:.1f} ms | {one * 1e3:.1f} ms | {split / one:.2f}x "
                f"| {'yes' if picked else 'no'} |"
            )
    lines += [
        "",
        f"Compile time (time to first result, batch 1000): `simulate` {first_sim:.2f} s; one optax Adam step "
        f"through it (forward + reverse) {first_step:.2f} s. `simulate`'s default torque-free path (no "
        f"`solver`: the closed form), eager in a fresh interpreter, 1000 bodies x 101 saved times: "
        f"{closed_form[0]:.2f} s, {closed_form[1]:.2f} s of it XLA's compilation; one optax Adam step through "
        f"it (final-attitude loss, jitted, the same interpreter after that call) {closed_form[2]:.2f} s, "
        f"{closed_form[3]:.2f} s of it XLA's.",
        "",
        f"Import time (fresh interpreters, least of 5): `import jax` {imported[0]:.2f} s; `import jaxquat` adds "
        f"{imported[1] * 1e3:.0f} ms; the first rotation function (`jq.multiply`) {imported[2] * 1e3:.0f} ms more, the "
        f"first solver (`jq.RKMK4`: diffrax, equinox, optimistix) {imported[3]:.2f} s more.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 1000, 100_000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--write", help="markdown file whose 'simulation' section to rewrite")
    ap.add_argument("--grad-batches", type=int, nargs="+", default=[1000, 100_000])
    a = ap.parse_args(argv)
    rows = throughput(a.batches, a.repeats)
    md = markdown(
        rows,
        gradient_table(a.grad_batches, a.repeats),
        compile_times(),
        import_times(),
        first_closed_form(),
        thread_table(a.repeats),
    )
    print(md)
    if a.write:
        write_section(a.write, "simulation", "## Simulation throughput, gradient cost, compile time\n\n" + md)


if __name__ == "__main__":
    main()
