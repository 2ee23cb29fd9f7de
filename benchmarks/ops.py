"""Rotation-op throughput: jaxquat against jaxlie, scipy (on JAX and on NumPy arrays) and
numpy-quaternion, as ratios, at several batch sizes, in float32 and float64, and under jax.grad.

Every contender runs in this process on the same inputs, jitted (scipy 1.17's
``Rotation`` traces under ``jax.jit`` with ``SCIPY_ARRAY_API=1``), timed after
compilation with ``block_until_ready()``; the figure is the least of repeated
runs in three rounds over each table (``run``). The roofline is a jitted
element-wise ``a + b`` over two ``(N, 4)`` arrays, the memory-traffic floor for
an op that reads two quaternion arrays and writes one.

    python benchmarks/ops.py [--n 1 1000 1000000] [--dtype float32 float64] [--no-grad] [--no-forward]
                             [--no-numpy] [--write docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("SCIPY_ARRAY_API", "1")  # must precede the scipy import
# XLA's constant folding spent minutes (per dtype) folding a (10^6, 4, 4) scatter-add that
# scipy's multiply leaves in its gradient; with the pass off every contender compiles in
# seconds (it folds nothing any of them needs at run time). Must precede the jax import.
os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_disable_hlo_passes=constant_folding").strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import jaxquat as jq  # noqa: E402
from _report import least_time, machine, write_section  # noqa: E402


def _xyzw(q):
    return jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _wxyz(q):
    return jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def brax_math():
    """brax's ``math`` module, loaded from its file (``import brax`` needs flax and more; its
    ``math`` needs only jax), or None when brax is not installed (``make bench`` installs it)."""
    import importlib.util

    spec = importlib.util.find_spec("brax")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = os.path.join(list(spec.submodule_search_locations)[0], "math.py")
    if not os.path.exists(path):
        return None
    module_spec = importlib.util.spec_from_file_location("brax_math", path)
    module = importlib.util.module_from_spec(module_spec)
    module_spec.loader.exec_module(module)
    return module


def contenders():
    """op -> {library: function of (p, q, v, m, t)} (each picks the inputs it needs).

    brax's functions take one quaternion each; they run under ``jax.vmap``, as brax
    users batch them. brax has no from_matrix, slerp, to_rotvec or mean; its Euler
    functions know one sequence, intrinsic x-y'-z'' (``"XYZ"``), in degrees one way.
    """
    bm = brax_math()
    vm = jax.vmap

    def brax(fn):
        return None if bm is None else fn

    def sp(q):
        return Rotation.from_quat(_xyzw(q))

    def lie(q):
        return jaxlie.SO3(wxyz=q)

    return {
        "multiply": {
            "jaxquat": lambda p, q, v, m, t: jq.multiply(p, q),
            "jaxlie": lambda p, q, v, m, t: (lie(p) @ lie(q)).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz((sp(p) * sp(q)).as_quat()),
            "brax": brax(lambda p, q, v, m, t: vm(bm.quat_mul)(p, q)),
        },
        "rotate": {
            "jaxquat": lambda p, q, v, m, t: jq.rotate(p, v),
            "jaxlie": lambda p, q, v, m, t: lie(p) @ v,
            "scipy": lambda p, q, v, m, t: sp(p).apply(v),
            "brax": brax(lambda p, q, v, m, t: vm(bm.rotate)(v, p)),
        },
        "to_matrix": {
            "jaxquat": lambda p, q, v, m, t: jq.to_matrix(p),
            "jaxlie": lambda p, q, v, m, t: lie(p).as_matrix(),
            "scipy": lambda p, q, v, m, t: sp(p).as_matrix(),
            "brax": brax(lambda p, q, v, m, t: vm(bm.quat_to_3x3)(p)),
        },
        "from_matrix": {
            "jaxquat": lambda p, q, v, m, t: jq.from_matrix(m),
            "jaxlie": lambda p, q, v, m, t: jaxlie.SO3.from_matrix(m).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.from_matrix(m).as_quat()),
        },
        "slerp": {
            "jaxquat": lambda p, q, v, m, t: jq.slerp(p, q, t),
            # Neither peer has an element-wise slerp; this is how each spells it.
            "jaxlie": lambda p, q, v, m, t: (
                (lie(p) @ jaxlie.SO3.exp(t[:, None] * (lie(p).inverse() @ lie(q)).log())).wxyz
            ),
            "scipy": lambda p, q, v, m, t: _wxyz(
                (sp(p) * Rotation.from_rotvec(t[:, None] * (sp(p).inv() * sp(q)).as_rotvec())).as_quat()
            ),
        },
        "to_rotvec": {
            "jaxquat": lambda p, q, v, m, t: jq.to_rotvec(p),
            "jaxlie": lambda p, q, v, m, t: lie(p).log(),
            "scipy": lambda p, q, v, m, t: sp(p).as_rotvec(),
        },
        "from_rotvec": {
            "jaxquat": lambda p, q, v, m, t: jq.from_rotvec(v),
            "jaxlie": lambda p, q, v, m, t: jaxlie.SO3.exp(v).wxyz,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.from_rotvec(v).as_quat()),
            # brax spells it as axis and angle
            "brax": brax(
                lambda p, q, v, m, t: vm(bm.quat_rot_axis)(
                    v / jnp.linalg.norm(v, axis=-1, keepdims=True), jnp.linalg.norm(v, axis=-1)
                )
            ),
        },
        "to_euler (xyz)": {
            "jaxquat": lambda p, q, v, m, t: jq.to_euler(p, "xyz"),
            "jaxlie": None,  # jaxlie has only roll/pitch/yaw (as_rpy_radians); not the same quantity set
            "scipy": lambda p, q, v, m, t: sp(p).as_euler("xyz"),
            "brax": brax(lambda p, q, v, m, t: vm(bm.quat_to_euler)(p)),  # its one sequence, "XYZ"
        },
        "from_euler (xyz)": {
            "jaxquat": lambda p, q, v, m, t: jq.from_euler(v, "xyz"),
            "jaxlie": None,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.from_euler("xyz", v).as_quat()),
            "brax": brax(lambda p, q, v, m, t: vm(bm.euler_to_quat)(v * (180 / jnp.pi))),  # "XYZ", degrees
        },
        "mean (of the batch)": {
            "jaxquat": lambda p, q, v, m, t: jq.mean(p),
            "jaxlie": None,
            "scipy": lambda p, q, v, m, t: _wxyz(sp(p).mean().as_quat()),
        },
        "align_vectors (batch of pairs)": {
            "jaxquat": lambda p, q, v, m, t: jq.align_vectors(v, jq.rotate(q, v)),
            "jaxlie": None,
            "scipy": lambda p, q, v, m, t: _wxyz(Rotation.align_vectors(sp(q).apply(v), v)[0].as_quat()),
            # brax's from_to takes unit vectors
            "brax": brax(
                lambda p, q, v, m, t: vm(bm.from_to)(
                    *(x / jnp.linalg.norm(x, axis=-1, keepdims=True) for x in (v, jq.rotate(q, v)))
                )
            ),
        },
    }


def numpy_contenders():
    """The same ops on NumPy arrays, not jitted: scipy's Rotation and numpy-quaternion."""
    import numpy as np
    import quaternion as nq
    from scipy.spatial.transform import Rotation as R

    def sp(q):
        return R.from_quat(np.roll(q, -1, -1))

    def nqa(q):
        return nq.as_quat_array(q)

    return {
        "multiply": {
            "scipy (NumPy)": lambda p, q, v, m, t: (sp(p) * sp(q)).as_quat(),
            "numpy-quaternion": lambda p, q, v, m, t: nqa(p) * nqa(q),
        },
        # (nq.rotate_vectors applies every rotation to every vector: an outer product, not this op)
        "rotate": {
            "scipy (NumPy)": lambda p, q, v, m, t: sp(p).apply(v),
            "numpy-quaternion": lambda p, q, v, m, t: nq.as_vector_part(
                nqa(p) * nq.from_vector_part(v) * nqa(p).conjugate()
            ),
        },
        "to_matrix": {
            "scipy (NumPy)": lambda p, q, v, m, t: sp(p).as_matrix(),
            "numpy-quaternion": lambda p, q, v, m, t: nq.as_rotation_matrix(nqa(p)),
        },
        "from_matrix": {
            "scipy (NumPy)": lambda p, q, v, m, t: R.from_matrix(m).as_quat(),
            "numpy-quaternion": lambda p, q, v, m, t: nq.from_rotation_matrix(m),
        },
        "slerp": {
            "scipy (NumPy)": lambda p, q, v, m, t: (
                sp(p) * R.from_rotvec(t[:, None] * (sp(p).inv() * sp(q)).as_rotvec())
            ).as_quat(),
            "numpy-quaternion": lambda p, q, v, m, t: nqa(p) * np.power(nqa(p).conjugate() * nqa(q), t),
        },
        "to_rotvec": {
            "scipy (NumPy)": lambda p, q, v, m, t: sp(p).as_rotvec(),
            "numpy-quaternion": lambda p, q, v, m, t: nq.as_rotation_vector(nqa(p)),
        },
        "from_rotvec": {
            "scipy (NumPy)": lambda p, q, v, m, t: R.from_rotvec(v).as_quat(),
            "numpy-quaternion": lambda p, q, v, m, t: nq.from_rotation_vector(v),
        },
        "to_euler (xyz)": {"scipy (NumPy)": lambda p, q, v, m, t: sp(p).as_euler("xyz"), "numpy-quaternion": None},
        "from_euler (xyz)": {
            "scipy (NumPy)": lambda p, q, v, m, t: R.from_euler("xyz", v).as_quat(),
            "numpy-quaternion": None,
        },
        "mean (of the batch)": {
            "scipy (NumPy)": lambda p, q, v, m, t: sp(p).mean().as_quat(),
            "numpy-quaternion": None,
        },
        "align_vectors (batch of pairs)": {
            "scipy (NumPy)": lambda p, q, v, m, t: R.align_vectors(sp(q).apply(v), v)[0].as_quat(),
            "numpy-quaternion": None,
        },
    }


# Which of (p, q, v, m, t) each op reads: with its output, the bytes its roofline moves.
READS = {
    "multiply": (0, 1),
    "rotate": (0, 2),
    "to_matrix": (0,),
    "from_matrix": (3,),
    "slerp": (0, 1, 4),
    "to_rotvec": (0,),
    "from_rotvec": (2,),
    "to_euler (xyz)": (0,),
    "from_euler (xyz)": (2,),
    "mean (of the batch)": (0,),
    "align_vectors (batch of pairs)": (1, 2),
}

# Under jax.grad: d sum(op) / d (its first array input); which input each op reads first.
GRAD_INPUT = {
    "multiply": 0,
    "rotate": 0,
    "to_matrix": 0,
    "from_matrix": 3,
    "slerp": 0,
    "to_rotvec": 0,
    "from_rotvec": 2,
    "to_euler (xyz)": 0,
    "from_euler (xyz)": 2,
    "mean (of the batch)": 0,
    "align_vectors (batch of pairs)": 2,
}


def _grad_of(fn, index):
    def total(*args):
        return jnp.sum(fn(*args))

    return jax.grad(total, argnums=index)


PEERS = ("jaxlie", "scipy", "brax", "scipy (NumPy)", "numpy-quaternion")


_ADD = jax.jit(lambda a, b: a + b)


def roofline_inputs(nbytes: int, dtype) -> tuple:
    """The inputs of a jitted ``a + b`` over flat arrays whose three buffers hold ``nbytes`` in all."""
    size = max(1, -(-nbytes // (3 * jnp.dtype(dtype).itemsize)))
    a = jnp.ones((size,), dtype)
    return a, a + 1


# Rounds over a whole table (run's docstring).
ROUNDS = 3


def run(n: int, dtype, repeats: int, grad: bool, numpy: bool = True, rounds: int = ROUNDS):
    """Times per op and library (seconds; None where a library lacks the op or fails to trace),
    and each op's roofline (the same bytes read and written by ``a + b``).

    Each JAX contender and each roofline is compiled once, then timed in ``rounds`` rounds, one
    after another over the whole table; its figure is the least of all its samples. A median of
    3 samples at 10^6 (one round, as before session 74) was taken by a disturbance of this shared
    2-core machine that lasted through a contender's samples: `multiply` in float32 read 26.8
    against 1.2 ms of roofline (brax 0.1x) in one run, 0.9-1.0 ms in isolation. The NumPy
    contenders run once (a call at 10^6 takes up to seconds)."""
    import numpy as np

    key = jax.random.PRNGKey(0)
    k1, k2, k3, k4 = jax.random.split(key, 4)
    p = jq.random(k1, (n,), dtype)
    q = jq.random(k2, (n,), dtype)
    v = jax.random.normal(k3, (n, 3), dtype)
    t = jax.random.uniform(k4, (n,), dtype)
    m = jax.jit(jq.to_matrix)(p)
    args = (p, q, v, m, t)
    np_args = tuple(np.asarray(x) for x in args)
    numpy_side = numpy_contenders() if numpy and not grad else {}
    timed = {}  # (op, lib) -> (jitted function, its arguments); lib "roofline": the op's a + b
    for op, libs in contenders().items():
        for lib, fn in libs.items():
            if fn is not None:
                timed[op, lib] = (jax.jit(_grad_of(fn, GRAD_INPUT[op]) if grad else fn), args)
        out = jax.eval_shape(timed[op, "jaxquat"][0], *args)
        moved = sum(args[i].nbytes for i in READS[op]) + out.size * out.dtype.itemsize
        timed[op, "roofline"] = (_ADD, roofline_inputs(moved, dtype))
    found: dict = {key_: [] for key_ in timed}  # each round's least sample
    for r in range(rounds):
        for key_, (fn, fn_args) in timed.items():
            if r and not found[key_]:
                continue  # failed in the first round
            try:
                found[key_].append(least_time(fn, *fn_args, repeats=repeats, warmup=0 if r else 1))
            except Exception:  # e.g. scipy's array-API path under jax.grad
                pass
    best = {key_: min(ts) if ts else None for key_, ts in found.items()}
    rows = []
    for op, libs in contenders().items():
        times = {lib: best.get((op, lib)) for lib in libs}
        for lib, fn in numpy_side.get(op, {}).items():
            try:
                times[lib] = (
                    None if fn is None else least_time(fn, *np_args, repeats=repeats, warmup=0, max_seconds=1.0)
                )
            except (TypeError, ValueError):  # e.g. numpy-quaternion's slerp takes one scalar t only
                times[lib] = None
        rows.append((op, times, best[op, "roofline"]))
    return rows


def table(n, dtype, rows, grad: bool) -> str:
    what = "`jax.grad` of the sum of each op's output (w.r.t. its first array input)" if grad else "each op"
    lines = [
        f"Batch {n:,}, {jnp.dtype(dtype).name}, {what}. Roofline: a jitted `a + b` moving the bytes the op "
        "reads and writes.",
        "",
        "| op | jaxquat (ms) | " + " | ".join(f"{p} / jaxquat" for p in PEERS) + " | jaxquat / roofline |",
        "|---|---:|" + "---:|" * (len(PEERS) + 1),
    ]
    for op, tm, roof in rows:
        ours = tm["jaxquat"]
        cells = ["n/a" if tm.get(p) is None else f"{tm[p] / ours:.1f}x" for p in PEERS]
        lines.append(f"| {op} | {ours * 1e3:.3f} | " + " | ".join(cells) + f" | {ours / roof:.2f} |")
    return "\n".join(lines) + "\n"


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return "not installed"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[1, 1000, 1_000_000])
    ap.add_argument("--dtype", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--no-grad", action="store_true")
    ap.add_argument("--no-forward", action="store_true", help="only the jax.grad tables")
    ap.add_argument(
        "--no-numpy",
        action="store_true",
        help="skip the NumPy contenders (on an accelerator they time the host)",
    )
    ap.add_argument("--write", help="markdown file whose 'ops' section to rewrite")
    a = ap.parse_args(argv)
    sections = [
        f"{machine()}; jaxlie {_version('jaxlie')}, scipy {_version('scipy')}, brax {_version('brax')} (math.py), "
        f"numpy-quaternion {_version('numpy-quaternion')}. "
        "Ratios: peer time / jaxquat time in the same run (above 1x: jaxquat is faster). Least of repeated runs "
        f"after compilation, in {ROUNDS} rounds over each table; JAX contenders jitted (XLA constant folding off "
        "for all), the NumPy ones (scipy on NumPy arrays, numpy-quaternion) called directly, in one round.",
    ]
    for dtype in a.dtype:
        jax.config.update("jax_enable_x64", dtype == "float64")
        for n in a.n:
            for grad in [False] * (not a.no_forward) + [True] * (not a.no_grad):
                reps = a.repeats if n < 1_000_000 else max(3, a.repeats // 3)
                rows = run(n, jnp.dtype(dtype), reps, grad, numpy=not a.no_numpy)
                md = table(n, dtype, rows, grad)
                print(md, flush=True)
                sections.append(md)
    if a.write:
        write_section(a.write, "ops", "## Rotation ops\n\n" + "\n".join(sections))
    return 0


if __name__ == "__main__":
    sys.exit(main())
