"""Shared strategies, references and tolerances for the jaxquat suite.

Hypothesis draws *seeds*, and each seed makes a fixed-shape batch, so every
jitted function compiles once per dtype and is reused across examples.
"""

from __future__ import annotations

import contextlib
from importlib.metadata import version

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
from hypothesis import strategies as st

X64 = bool(jax.config.jax_enable_x64)
DTYPE = jnp.float64 if X64 else jnp.float32
NP_DTYPE = np.float64 if X64 else np.float32
# Tolerances for values of O(1): float64 near rounding, float32 a few ulps times condition.
TOL = 1e-10 if X64 else 2e-5
BATCH = 16
# XLA's CPU emitters can be chosen (``xla_cpu_use_fusion_emitters``) before jaxlib 0.11, whose XLA
# has the fusion emitters only and no longer knows the option (``conftest.py``).
XLA_CHOOSES_EMITTERS = tuple(int(v) for v in version("jaxlib").split(".")[:2]) < (0, 11)

seeds = st.integers(min_value=0, max_value=2**31 - 1)


def xla_fuses_multiply_add() -> bool:
    """Whether XLA's compiled code rounds ``a * b - c`` once (a fused multiply-add: on a CPU with
    FMA, x86-64 since 2013 and every ARM64 one, and on GPUs) or twice: ``a = 1 + 2^-12`` (float32;
    ``2^-27`` in float64), ``c = 1 + 2^-11`` (``2^-26``): ``a a - c`` is the last half ulp of
    ``a a``, which rounding the product first loses. A few of ``jaxquat._trig``'s bounds hold
    only with one rounding (``tests/test_trig.py``)."""
    h = 2.0 ** (-27 if X64 else -12)
    a, c = jnp.asarray(1.0 + h, DTYPE), jnp.asarray(1.0 + 2 * h, DTYPE)
    return float(_multiply_subtract(a, c)) != 0.0


@jax.jit
def _multiply_subtract(a, c):
    return a * a - c


def singular_quats(dtype=np.float64) -> np.ndarray:
    """The points where naive formulas break: identity, tiny angles, 180 degrees, sign flips."""
    s = np.sqrt(0.5)
    rows = [
        [1, 0, 0, 0],
        [-1, 0, 0, 0],
        [np.cos(5e-9), np.sin(5e-9), 0, 0],  # angle 1e-8
        [np.cos(5e-9), 0, -np.sin(5e-9) * s, np.sin(5e-9) * s],
        [0, 1, 0, 0],  # 180 degrees
        [0, 0, 1, 0],
        [0, 0, 0, 1],
        [0, s, s, 0],
        [0, -s, 0, s],
        [1e-9, 1, 0, 0],  # just off 180
        [-1e-9, 0, 1, 0],
        [s, s, 0, 0],  # 90 degrees
    ]
    q = np.asarray(rows, dtype=np.float64)
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(dtype)


def random_quats(seed: int, n: int = BATCH, with_singular: bool = True, dtype=None) -> np.ndarray:
    """``n`` random unit quaternions; with ``with_singular`` the first rows are the singular set."""
    dtype = NP_DTYPE if dtype is None else dtype
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    if with_singular:
        sing = singular_quats()
        k = rng.integers(0, 4)  # a different few singular rows each example
        idx = (np.arange(min(4, n)) * 3 + k) % len(sing)
        q[: len(idx)] = sing[idx]
    return q.astype(dtype)


def random_vectors(seed: int, n: int = BATCH, dtype=None) -> np.ndarray:
    dtype = NP_DTYPE if dtype is None else dtype
    return np.random.default_rng(seed + 1).normal(size=(n, 3)).astype(dtype)


def to_scipy(q) -> np.ndarray:
    """jaxquat (w, x, y, z) -> scipy (x, y, z, w), in float64."""
    return np.asarray(q, dtype=np.float64)[..., [1, 2, 3, 0]]


def from_scipy(q) -> np.ndarray:
    return np.asarray(q, dtype=np.float64)[..., [3, 0, 1, 2]]


def assert_same_rotation(p, q, tol=None):
    """``p`` and ``q`` are the same rotation: ``p = +-q`` element-wise."""
    tol = TOL if tol is None else tol
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    err = np.minimum(np.abs(p - q).max(-1), np.abs(p + q).max(-1))
    assert np.all(err <= tol), f"max rotation mismatch {err.max():.3e} > {tol:.1e}"


def assert_close(a, b, tol=None, what=""):
    tol = TOL if tol is None else tol
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape, f"{what}: shape {a.shape} != {b.shape}"
    err = np.abs(a - b).max() if a.size else 0.0
    assert err <= tol, f"{what}: max abs error {err:.3e} > {tol:.1e}"


def on_device(a, dtype=None) -> jax.Array:
    """``a`` converted in NumPy (to ``dtype`` if given), then placed on the device: the array
    ``jnp.asarray(a, dtype)`` makes (the same dtype under either x64 flag), without the program
    ``jnp.asarray`` of a NumPy array compiles for every new shape and dtype in jax 0.10.2 (a copy,
    or a conversion; about 20 ms each on a 2-core CPU, about 230 of them per pass in the tests
    that now call this, session 41)."""
    return jax.device_put(np.asarray(a, dtype))


def central_difference_jacobian(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Jacobian of ``f`` at ``x`` (float64) by central differences: shape out.shape + x.shape.
    The points go to the device by :func:`on_device`."""
    x = np.asarray(x, dtype=np.float64)
    f0 = np.asarray(f(on_device(x)))
    jac = np.zeros(f0.shape + x.shape)
    flat = x.reshape(-1)
    for i in range(flat.size):
        e = np.zeros_like(flat)
        e[i] = h
        fp = np.asarray(f(on_device((flat + e).reshape(x.shape))))
        fm = np.asarray(f(on_device((flat - e).reshape(x.shape))))
        jac.reshape(f0.shape + (-1,))[..., i] = (fp - fm) / (2 * h)
    return jac


# ---------------------------------------------------------------- smooth attitude curves
# Kinematic relations are checked against autodiff: q(t) from a smooth rotation-vector
# curve, its derivatives by jax.jacfwd in t. Each seed picks different coefficients.


def curve_coefficients(seed: int, n: int = BATCH) -> np.ndarray:
    """Per-element coefficients ``(n, 3, 3)``: rotvec_k(t) = c0 + c1 t + c2 sin(2 t + k)."""
    return np.random.default_rng(seed + 17).normal(size=(n, 3, 3))


def rotvec_curve(c, t):
    k = jnp.broadcast_to(jnp.arange(3, dtype=c.dtype), c.shape[:-2] + (3,))
    return c[..., 0, :] + c[..., 1, :] * t + c[..., 2, :] * jnp.sin(2 * t + k)


def attitude_curve(c, t, scale=0.0):
    """Unit-quaternion curve, times ``1 + 0.3 scale sin(3 t)`` (``scale = 1``: |q| varies)."""
    import jaxquat as jq

    return jq.from_rotvec(rotvec_curve(c, t)) * (1.0 + 0.3 * scale * jnp.sin(3.0 * t))


def time_derivatives(f, t, order: int):
    """``[f(t), f'(t), ..., f^(order)(t)]`` by nested forward-mode autodiff in scalar ``t``."""
    out = [f(t)]
    g = f
    for _ in range(order):
        g = jax.jacfwd(g)
        out.append(g(t))
    return out


def random_inertias(seed: int, n: int = BATCH, dtype=None) -> np.ndarray:
    """Physical full (non-diagonal) inertia tensors: random point clouds, ``(n, 3, 3)``."""
    dtype = NP_DTYPE if dtype is None else dtype
    rng = np.random.default_rng(seed + 5)
    r = rng.normal(size=(n, 6, 3)) * rng.uniform(0.3, 2.0, (n, 1, 3))
    r -= r.mean(axis=1, keepdims=True)
    m = rng.uniform(0.5, 2.0, (n, 6))
    eye = np.eye(3)
    inertia = np.einsum(
        "nk,nkij->nij", m, np.einsum("nk,ij->nkij", (r * r).sum(-1), eye) - np.einsum("nki,nkj->nkij", r, r)
    )
    inertia /= (np.trace(inertia, axis1=-2, axis2=-1) / 3.0)[:, None, None]  # O(1) entries
    return inertia.astype(dtype)


def dop853_reference(q0, w0, moments, ts):
    """Independent reference for a torque-free body with principal ``moments``: the raw
    7-state ODE in NumPy, scipy DOP853 at rtol = atol = 1e-13, at times ``ts`` (ascending
    from 0, or descending from 0 for backward runs). Returns ``(q, w)`` in float64."""
    from scipy.integrate import solve_ivp

    moments = np.asarray(moments, np.float64)

    def rhs(t, y):
        q, w = y[:4], y[4:]
        qd = 0.5 * np.array([-q[1:] @ w, *(q[0] * w + np.cross(q[1:], w))])
        return np.concatenate([qd, np.cross(moments * w, w) / moments])

    ts = np.asarray(ts, np.float64)
    y0 = np.concatenate([np.asarray(q0, np.float64), np.asarray(w0, np.float64)])
    end = ts[np.argmax(np.abs(ts))]
    sol = solve_ivp(rhs, (0.0, end), y0, method="DOP853", rtol=1e-13, atol=1e-13, t_eval=ts)
    return sol.y[:4].T, sol.y[4:].T


def run_example_in_process(script: str, *args: str) -> str:
    """Run an example's ``main`` in this process with ``sys.argv`` set; its stdout (an example
    that switches float64 on belongs in the float64 pass, one in float32 in the float32 pass).
    No interpreter and JAX start-up per example (about 3 s each), and where a test module has
    already compiled the same jitted solver the example reuses it instead of tracing and
    compiling anew. The example runs with the suite's rank promotion (``"raise"``; a user's
    default is ``"allow"``, which every example also meets): JAX's compilation cache is keyed on
    it, so under ``"allow"`` the example compiled every solver of the test module again (the
    time-optimal example 25.1 s against 1.9 s)."""
    import contextlib
    import io
    import pathlib
    import runpy
    import sys

    root = pathlib.Path(__file__).parent.parent
    path = root / script
    argv, sys.argv = sys.argv, [str(path), *args]
    sys.path.insert(0, str(path.parent))
    buffer = io.StringIO()
    try:
        with contextlib.redirect_stdout(buffer):
            runpy.run_path(str(path), run_name="__main__")
    finally:
        sys.argv = argv
        sys.path.remove(str(path.parent))
    return buffer.getvalue()


def execute_notebook(path) -> None:
    """Run the notebook at ``path`` top to bottom in a fresh kernel (cwd: its folder; the kernel
    inherits the environment, the test worker's XLA flags among it); a failing cell
    raises ``CellExecutionError`` with its traceback."""
    import nbclient
    import nbformat

    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}
    )
    client.execute()
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.get("output_type") == "error"
    ]
    assert not errors


def run_notebook_in_process(path) -> str:
    """Run a notebook's jupytext source (``NAME.py`` beside ``NAME.ipynb``; the suite checks they
    are the same cells) top to bottom in this process, from the notebook's folder, under the
    suite's rank promotion; its stdout. Like :func:`run_example_in_process`: no kernel start-up
    and imports (measured: the estimation notebook 10.0 s against 16.3 s in a kernel), and the
    solvers a test module has already compiled are reused."""
    import contextlib
    import io
    import os
    import runpy

    import matplotlib

    matplotlib.use("Agg")  # the kernel's inline backend draws; here plt.show() is a no-op
    import sys

    source = path.with_suffix(".py").resolve()
    cwd, search = os.getcwd(), list(sys.path)
    buffer = io.StringIO()
    try:
        os.chdir(source.parent)
        with contextlib.redirect_stdout(buffer):
            runpy.run_path(str(source), run_name="__main__")
    finally:
        os.chdir(cwd)
        sys.path[:] = search  # a notebook may add its folder's parent
    return buffer.getvalue()


def jaxpr_equations(jaxpr):
    """Every equation of ``jaxpr`` (a ``jax.extend.core.Jaxpr``) and of the jaxprs inside it
    (scan and while bodies, ``jit`` calls, custom rules), depth first."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, (list, tuple)) else [param]:
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    yield from jaxpr_equations(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    yield from jaxpr_equations(sub)


@contextlib.contextmanager
def lowered_programs():
    """The names of the programs lowered (traced and compiled, or taken from the compilation
    cache) inside the ``with`` block, from JAX's monitoring events."""
    names: list = []

    def listener(event, seconds, **kwargs):
        if event.endswith("jaxpr_to_mlir_module_duration"):
            names.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


class ChunkSeen(Exception):
    """Raised by :func:`spy_on_chunk_sizes`' spy: the chunk size is recorded, nothing solved."""


def spy_on_chunk_sizes(monkeypatch) -> list[int]:
    """Replace ``numerical_solve._in_chunks`` by a spy that appends each solve's chunk size to the
    returned list and raises :class:`ChunkSeen`: nothing is solved or compiled."""
    from jaxquat.integration import numerical_solve

    sizes: list[int] = []

    def spy(solve, size, *args, **kwargs):
        sizes.append(size)
        raise ChunkSeen

    monkeypatch.setattr(numerical_solve, "_in_chunks", spy)
    return sizes
