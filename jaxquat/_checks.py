"""Argument validation at trace time.

Shapes and dtypes are static under ``jit``, so every check here runs once per
trace and costs nothing at run time. Each error names the argument and the shape
it expected, so a user who passes an ``(n, 3)`` vector where an ``(n, 4)``
quaternion belongs is told so before anything is computed.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.core import Tracer


def as_float_array(x: Any, name: str) -> Array:
    """Convert ``x`` to a JAX array and require a floating dtype.

    Python floats and lists of real numbers are accepted and become *weakly typed* arrays
    of JAX's default float dtype, as Python scalars are: combined with a float32 array
    they take float32 (``rotate(q_float32, [1.0, 0.0, 0.0])`` is float32, not float64).
    Integer, boolean and complex arrays, and lists of booleans or complex numbers,
    raise ``TypeError``: silently promoting integer quaternions hides bugs (and the
    gradients are meaningless), and a complex value would lose its imaginary part.

    Python numbers and floating NumPy arrays go to the device by ``jax.device_put`` (the same
    dtype, weak type and values as ``jnp.asarray``): ``jnp.asarray`` of them is a compiled
    operation (``stage``), one more single-operation compilation for every new shape of an
    eager call.
    """
    if isinstance(x, (float, int)) and not isinstance(x, bool):
        return jax.device_put(float(x))
    if isinstance(x, (np.ndarray, np.floating)) and np.issubdtype(x.dtype, np.floating):
        return jax.device_put(x)
    if isinstance(x, (list, tuple)):
        x = _weak_list(x)
    arr = jnp.asarray(x)
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        raise TypeError(
            f"argument '{name}' must have a floating dtype (float16, bfloat16, float32 or float64), got {arr.dtype}"
        )
    return arr


def _plain_numbers(x: Any) -> bool:
    """Whether ``x`` is a (nested) list or tuple of Python numbers only."""
    if isinstance(x, (list, tuple)):
        return all(_plain_numbers(e) for e in x)
    return isinstance(x, (bool, int, float, complex))


def _weak_list(x: list | tuple) -> Array:
    """A (nested) list of real numbers as a weakly typed array of the default float dtype.

    JAX makes only Python scalars weak; a list becomes a strong float64 array under x64 and
    promotes everything it meets. Stacking weak scalars keeps the list weak. Lists longer
    than 4096 numbers become ordinary (strong) arrays: at that size an array is the
    expected input, and stacking would be slow.
    """
    if not _plain_numbers(x):  # arrays or tracers inside: their own dtypes decide, as in JAX
        arr = jnp.asarray(x)
        return arr.astype(jnp.asarray(0.0).dtype) if jnp.issubdtype(arr.dtype, jnp.integer) else arr
    values = np.asarray(x)
    if values.dtype == bool or np.issubdtype(values.dtype, np.complexfloating) or values.dtype == object:
        return jnp.asarray(x)  # rejected with a clear message by the caller
    values = values.astype(np.float64)
    if values.size == 0 or values.size > 4096:
        return jnp.asarray(values, dtype=jnp.asarray(0.0).dtype)
    flat = jnp.stack([jnp.asarray(float(v)) for v in values.ravel()])
    return flat.reshape(values.shape)


def working_dtype(dtype) -> Any:
    """The dtype to compute in: float32 for the half-precision dtypes (float16, bfloat16),
    whose 3 significant digits and small exponent range the elliptic functions, ``eigh``
    and the spline's linear solve cannot work in (XLA has no half-precision ``eigh`` or
    LU); the dtype itself otherwise. Results are cast back to the input dtype."""
    return jnp.float32 if jnp.finfo(dtype).bits < 32 else dtype


def _check_trailing(arr: Array, name: str, trailing: tuple[int, ...], what: str) -> Array:
    n = len(trailing)
    if arr.ndim < n or tuple(arr.shape[arr.ndim - n :]) != trailing:
        expected = "(..., " + ", ".join(str(t) for t in trailing) + ")"
        raise ValueError(f"argument '{name}' must be {what} shaped {expected}, got shape {tuple(arr.shape)}")
    return arr


def quat(q: Any, name: str = "q") -> Array:
    """Validate a quaternion argument: floating, shaped ``(..., 4)``."""
    return _check_trailing(as_float_array(q, name), name, (4,), "a quaternion array")


def vec3(v: Any, name: str = "v") -> Array:
    """Validate a 3-vector argument: floating, shaped ``(..., 3)``."""
    return _check_trailing(as_float_array(v, name), name, (3,), "a 3-vector array")


def mat3(m: Any, name: str = "m") -> Array:
    """Validate a 3x3 matrix argument: floating, shaped ``(..., 3, 3)``."""
    return _check_trailing(as_float_array(m, name), name, (3, 3), "a matrix array")


def scalar_like(x: Any, name: str) -> Array:
    """Validate a batch of scalars (any shape, floating)."""
    return as_float_array(x, name)


def per_item(x: Any, name: str, items: Array, items_name: str) -> Array:
    """Validate one scalar per item: ``x`` shaped ``(..., n)`` where ``items`` is ``(..., n, k)``."""
    x = scalar_like(x, name)
    if x.shape[-1:] != items.shape[-2:-1]:
        raise ValueError(
            f"argument '{name}' must be shaped (..., n) with n = {items.shape[-2]} (one per row of "
            f"'{items_name}' {tuple(items.shape)}), got shape {tuple(x.shape)}"
        )
    return x


def require_tqdm(function: str) -> None:
    """``progress=True`` needs tqdm, an optional dependency (``pip install 'jaxquat[progress]'``)."""
    try:
        import tqdm  # noqa: F401
    except ImportError:
        raise ImportError(
            f"{function}(progress=True) needs tqdm, an optional dependency: pip install 'jaxquat[progress]'"
        ) from None


def is_traced(x: Any) -> bool:
    """Whether ``x`` is a tracer (its values unknown: inside ``jit``, ``vmap`` or ``grad``)."""
    return isinstance(x, Tracer)


@contextlib.contextmanager
def compile_time_eval() -> Iterator[None]:
    """Within it, JAX operations on concrete values return concrete arrays, also while a caller's
    ``jit`` or ``jax.shard_map`` is tracing. ``jax.ensure_compile_time_eval`` does it under ``jit``
    only: inside a ``shard_map`` body (jax 0.10.2) ``jnp.asarray`` of a NumPy array still returned
    a ``ShardMapTracer``, and ``simulate`` with a NumPy inertia raised ``TypeError`` there. JAX's
    evaluation context (``jax._src.core.eval_context``, no public API) does it in both; where a
    JAX version lacks it, only the public context."""
    try:
        from jax._src.core import eval_context
    except ImportError:  # pragma: no cover - a JAX without it
        eval_context = contextlib.nullcontext
    with jax.ensure_compile_time_eval(), eval_context():
        yield


def concrete(x: Any) -> np.ndarray | None:
    """The values of ``x`` when they are known at trace time (an eager call), else ``None``."""
    if is_traced(x):
        return None
    return np.asarray(x)


def nonempty(x: Array, name: str, axis: int, what: str) -> Array:
    """Require a non-empty set along ``axis`` (a shape check, so at trace time)."""
    if x.shape[axis] == 0:
        raise ValueError(f"argument '{name}' must hold at least one {what}, got shape {tuple(x.shape)}")
    return x


def weights(w: Array, name: str = "weights") -> Array:
    """Per-item weights: where their values are known (an eager call), every weight must be
    finite and non-negative with a positive sum per set. Traced weights are checked by the
    caller, which returns NaN for a set whose weights are invalid."""
    values = concrete(w)
    if values is not None:
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            raise ValueError(f"argument '{name}' must be finite and non-negative, got {values}")
        if np.any(values.sum(axis=-1) <= 0):
            raise ValueError(f"argument '{name}' must have a positive sum in every set, got {values}")
    return w


def vector_pairs(a: Any, b: Any, w: Any, names: tuple[str, str]) -> tuple[Array, Array, Array | None]:
    """Validate a Wahba problem's arguments: two vector sets shaped ``(..., n, 3)`` with the same
    ``n >= 1`` and optional per-pair weights ``w`` ``(..., n)`` (argument ``weights``, checked as
    :func:`weights`), all broadcast to one batch shape. ``w`` stays None when not given."""
    a, b = vec3(a, names[0]), vec3(b, names[1])
    if a.ndim < 2 or b.ndim < 2 or a.shape[-2] != b.shape[-2]:
        raise ValueError(
            f"arguments '{names[0]}' and '{names[1]}' must be shaped (..., n, 3) with the same n, "
            f"got {tuple(a.shape)} and {tuple(b.shape)}"
        )
    nonempty(a, names[0], -2, "vector pair (n >= 1 in (..., n, 3))")
    if w is None:
        a, b = broadcast_batch([a, b], list(names), [2, 2])
        return a, b, None
    w = weights(per_item(w, "weights", a, names[0]))
    a, b, w = broadcast_batch([a, b, w], [*names, "weights"], [2, 2, 1])
    return a, b, w


# The kinds of argument `arguments` validates: the check, and the number of trailing core axes
# (the rest are batch axes).
_KINDS = {
    "quaternion": (lambda x, n: quat(x, n), 1),
    "vector": (lambda x, n: vec3(x, n), 1),
    "matrix": (lambda x, n: mat3(x, n), 2),
    "inertia": (lambda x, n: inertia(x, n), 2),
    "scalar": (lambda x, n: scalar_like(x, n), 0),
    # one per item of a set: (..., n, 4), (..., n, 3), (..., n)
    "quaternions": (lambda x, n: quat(x, n), 2),
    "vectors": (lambda x, n: vec3(x, n), 2),
    "scalars": (lambda x, n: scalar_like(x, n), 1),
}


def arguments(*, shared: tuple[str, ...] | bool = (), **named: tuple[Any, str]) -> list[Array]:
    """Validate a function's array arguments and broadcast their batch axes: the one
    validate-and-broadcast step of every public function.

    Each keyword is the argument's name (as errors print it) and its value a pair
    ``(value, kind)``, kind one of ``"quaternion"`` ``(..., 4)``, ``"vector"`` ``(..., 3)``,
    ``"matrix"`` / ``"inertia"`` ``(..., 3, 3)`` or ``"scalar"`` ``(...)``, or a set of one
    of those per item, ``"quaternions"`` ``(..., n, 4)``, ``"vectors"`` ``(..., n, 3)`` or
    ``"scalars"`` ``(..., n)`` (the set's axis ``n`` is not broadcast). Returns the
    arrays in keyword order, in one dtype, their batch axes broadcast to one shape and their
    core axes kept. An argument already validated further (an inertia's values) passes
    through its shape check unchanged. An argument named in ``shared`` that has no batch axes
    (one inertia tensor for a batch of bodies) is returned as it is, in the common dtype, not
    broadcast: a kernel that reads its entries as scalars broadcasts them inside its loop, where
    the broadcast array was written to memory and read back (:func:`broadcast_batch`).
    ``shared=True`` names every argument.
    """
    arrays, cores = [], []
    for name, (value, kind) in named.items():
        check, core = _KINDS[kind]
        arrays.append(check(value, name))
        cores.append(core)
    return broadcast_batch(arrays, list(named), cores, tuple(named) if shared is True else shared or ())


def optional_arguments(*, shared: tuple[str, ...] | bool = (), **named: tuple[Any, str]) -> list[Array | None]:
    """:func:`arguments` where an argument whose kind ends in ``?`` (``"vector?"``) may be ``None``
    (an omitted optional one): it is returned as ``None`` and takes no part in the broadcast, so a
    compiled body forms the default (a zero torque, a body-fixed point's zero velocity) inside its
    program, with no eager operation before it (``jnp.zeros`` outside is a single-operation
    compilation for every new shape). ``None`` for any other argument fails its check as usual."""
    given = {n: (v, k.removesuffix("?")) for n, (v, k) in named.items() if not (v is None and k.endswith("?"))}
    checked = dict(zip(given, arguments(shared=shared, **given)))
    return [checked.get(name) for name in named]


def broadcast_batch(
    arrays: list[Array], names: list[str], core_ndims: list[int], shared: tuple[str, ...] = ()
) -> list[Array]:
    """Broadcast the leading (batch) axes of several arrays, keeping their core axes.

    ``core_ndims[i]`` is the number of trailing axes of ``arrays[i]`` that are not
    batch axes (1 for a quaternion, 2 for a matrix, 0 for a scalar). The result
    arrays share one dtype and one batch shape, except those named in ``shared`` that have no
    batch axes: they keep none. Measured on the inertia of the dynamics' public functions (a
    tensor ``(3, 3)`` for 10^6 bodies, float32, one core, least of 11, session 62): the
    broadcast tensor ``(10^6, 3, 3)`` was written and read back, ``angular_momentum`` in the
    space frame 34-38 -> 12-16 ms, ``angular_acceleration`` 16-35 -> 4-9 ms and its gradient in
    the inertia 89-94 -> 14-15 ms. ``rotate``, ``angle_between``, ``power`` and ``slerp`` name all
    their arguments (session 63; one vector, rotation, exponent or start for a batch, 10^6 rows,
    float32, one core): ``rotate(Q, v)`` eager 4.8-6.2 -> 2.7 ms, its gradient 16.5-17.1 -> 7.9-9.6
    ms; ``angle_between(Q, q)`` eager 8.7-9.2 -> 4.1-5.6 ms, gradient 107-114 -> 53-78 ms; under
    ``jit`` the values' times are unchanged (XLA fuses the broadcast there). A kernel formed from
    rows of one shape (``multiply``, ``plus``, ``minus``, the kinematics, ...) names its arguments
    too, and has them broadcast inside its compiled program (``_arrays.compiled_rows_broadcast``).
    """
    batches = [a.shape[: a.ndim - c] for a, c in zip(arrays, core_ndims)]
    try:
        batch = jnp.broadcast_shapes(*batches)
    except ValueError:
        desc = ", ".join(f"'{n}' {tuple(a.shape)}" for n, a in zip(names, arrays))
        raise ValueError(f"batch shapes do not broadcast: {desc}") from None
    dtype = jnp.result_type(*arrays)
    return [
        a.astype(dtype)
        if name in shared and a.ndim == c
        else jnp.broadcast_to(a, batch + a.shape[a.ndim - c :]).astype(dtype)
        for a, c, name in zip(arrays, core_ndims, names)
    ]


EULER_SEQUENCES = tuple(
    s
    for case in (str.lower, str.upper)
    for s in (case(a + b + c) for a in "xyz" for b in "xyz" for c in "xyz" if a != b and b != c)
)


def euler_seq(seq: Any) -> str:
    """Validate an Euler axis sequence as scipy spells it.

    Lower case (``"xyz"``) is extrinsic (rotations about the fixed axes),
    upper case (``"XYZ"``) intrinsic (about the moving axes). Consecutive axes
    must differ; twelve sequences in each case.
    """
    if not isinstance(seq, str) or seq not in EULER_SEQUENCES:
        raise ValueError(
            f"argument 'seq' must be one of the 24 Euler sequences: three of 'xyz' "
            f"(extrinsic) or three of 'XYZ' (intrinsic), no two consecutive axes "
            f"equal, e.g. 'xyz', 'ZYX', 'zxz'; got {seq!r}"
        )
    return seq


def float_dtype(dtype: Any):
    """Validate a ``dtype`` argument; ``None`` means JAX's default float dtype."""
    dtype = jnp.asarray(0.0).dtype if dtype is None else jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"argument 'dtype' must be a floating dtype, got {dtype}")
    return dtype


FRAMES = ("body", "space")


def frame(value: Any, name: str = "frame") -> str:
    """Validate a frame argument: ``"body"`` or ``"space"``."""
    if not isinstance(value, str) or value not in FRAMES:
        raise ValueError(f"argument '{name}' must be 'body' or 'space', got {value!r}")
    return value


def inertia(m: Any, name: str = "inertia") -> Array:
    """Validate an inertia-tensor argument's type and shape: floating, ``(..., 3, 3)``.

    Values are checked separately (:func:`jaxquat.check_inertia`), because they
    are only known outside ``jit``.
    """
    return _check_trailing(as_float_array(m, name), name, (3, 3), "an inertia tensor array")
