"""Euler angles: all 24 conventions against scipy, round trips, gimbal lock in both dtypes."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from scipy.spatial.transform import Rotation

import jaxquat as jq
from helpers import DTYPE, TOL, assert_close, assert_same_rotation, from_scipy, random_quats, seeds, to_scipy

SEQUENCES = [a + b + c for a in "xyz" for b in "xyz" for c in "xyz" if a != b and b != c]
SEQUENCES = SEQUENCES + [s.upper() for s in SEQUENCES]
assert len(SEQUENCES) == 24

_to = {s: jax.jit(lambda q, s=s: jq.to_euler(q, s)) for s in SEQUENCES}
_from = {s: jax.jit(lambda a, s=s: jq.from_euler(a, s)) for s in SEQUENCES}
_jacobian = {s: jax.jit(jax.jacrev(lambda q, s=s: jq.to_euler(q, s))) for s in SEQUENCES}


@pytest.mark.parametrize("seq", SEQUENCES)
def test_against_scipy(seq):
    q = random_quats(seq.__hash__() % 1000, n=64, with_singular=False)
    ang = np.asarray(_to[seq](q))
    ref = Rotation.from_quat(to_scipy(q)).as_euler(seq)
    # Compare angles away from the +-pi wrap of the outer angles.
    ok = np.all(np.abs(np.abs(ref) - np.pi) > 1e-3, axis=-1)
    assert_close(ang[ok], ref[ok], tol=100 * TOL)
    assert_same_rotation(_from[seq](ang), q, tol=20 * TOL)
    assert_same_rotation(
        _from[seq](ref.astype(DTYPE)), from_scipy(Rotation.from_euler(seq, ref).as_quat()), tol=20 * TOL
    )


@pytest.mark.parametrize("seq", SEQUENCES)
def test_gimbal_lock_round_trip(seq):
    """Middle angle at, and within 1e-4 degrees of, the singular value; float32 too. The rows run
    padded to test_against_scipy's 64 (its compiled programs) and the Jacobian is one compiled
    program per sequence (eager ``jax.jacrev`` and the rows' own shape compiled about 100 small
    programs: 15.0 s of the float64 pass's test time for the 24 sequences on a 2-core EPYC, now
    4.8 s)."""
    symmetric = seq[0].lower() == seq[2].lower()
    singular = [0.0, np.pi] if symmetric else [-np.pi / 2, np.pi / 2]
    delta = np.deg2rad(1e-4)
    rng = np.random.default_rng(1)
    rows = []
    for s in singular:
        for d in (0.0, delta, -delta):
            mid = s + d
            if symmetric and not (0 <= mid <= np.pi):
                continue
            a, c = rng.uniform(-np.pi, np.pi, size=2)
            rows.append([a, mid, c])
    angles = np.asarray(rows)
    q = from_scipy(Rotation.from_euler(seq, angles).as_quat()).astype(DTYPE)
    # On 64 rows (the rows repeated), test_against_scipy's shape: its compiled programs.
    padded = np.asarray(_to[seq](np.resize(q, (64, 4))))  # sliced in NumPy: no eager slice programs
    out = padded[: len(q)]
    assert np.all(np.isfinite(out))
    back = np.asarray(_from[seq](padded))[: len(q)]
    # Rotation reproduced to rounding: 1e-4 degrees is far larger than this tolerance.
    assert_same_rotation(back, q, tol=20 * TOL)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = Rotation.from_quat(to_scipy(q)).as_euler(seq)
    assert_close(out[:, 1], ref[:, 1], tol=1e-3)
    # Gradients are finite at gimbal lock.
    g = _jacobian[seq](q[0])
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("seq", ["xyz", "ZXZ", "zyx", "XZX"])
def test_gimbal_lock_is_the_middle_angle_within_ten_eps(seq):
    """The lock branch (third angle 0, the first carrying the rotation) is taken where the middle
    angle is within ``10 eps`` of its singular value and not at 1.5 times that: the rule, tested on
    ``|c, d|^2 <= (5 eps)^2 |a, b|^2`` and its mirror, without computing the angle (session 75)."""
    tol = 10 * float(np.finfo(DTYPE).eps)
    symmetric = seq[0].lower() == seq[2].lower()
    singular = [0.0, np.pi] if symmetric else [-np.pi / 2, np.pi / 2]
    rows, locked = [], []
    for s in singular:
        inward = 1.0 if s == singular[0] else -1.0
        for k in (0.5, 1.5):
            rows.append([0.7, s + inward * k * tol, -1.1])
            locked.append(k < 1)
    q = from_scipy(Rotation.from_euler(seq, np.asarray(rows)).as_quat()).astype(DTYPE)
    out = np.asarray(_to[seq](np.resize(q, (64, 4))))[: len(q)]
    np.testing.assert_array_equal(out[:, 2] == 0.0, np.asarray(locked))
    assert_same_rotation(np.asarray(_from[seq](np.resize(out, (64, 3))))[: len(q)], q, tol=20 * TOL)


@given(seeds)
def test_euler_round_trip_property(seed):
    """64 rows, as ``test_against_scipy``: its compiled programs serve every example here (the
    helpers' batch and 16 angle rows compiled four programs for each sequence drawn: 28 per
    pass, 7.5 s of the float64 pass's test time, session 41)."""
    rng = np.random.default_rng(seed)
    seq = SEQUENCES[seed % 24]
    q = random_quats(seed, n=64)
    assert_same_rotation(_from[seq](_to[seq](q)), q, tol=20 * TOL)
    # Angles drawn inside the principal ranges come back unchanged.
    symmetric = seq[0].lower() == seq[2].lower()
    mid = rng.uniform(0.1, np.pi - 0.1, 64) if symmetric else rng.uniform(-1.4, 1.4, 64)
    angles = np.stack([rng.uniform(-3.0, 3.0, 64), mid, rng.uniform(-3.0, 3.0, 64)], -1).astype(DTYPE)
    assert_close(_to[seq](_from[seq](angles)), angles, tol=100 * TOL)


def test_known_values():
    # 90 degrees about z, extrinsic xyz: (0, 0, pi/2).
    q = jnp.asarray([np.sqrt(0.5), 0, 0, np.sqrt(0.5)], DTYPE)
    assert_close(jq.to_euler(q, "xyz"), [0, 0, np.pi / 2], tol=10 * TOL)
    # Intrinsic ZYX (yaw, pitch, roll) of yaw 30 deg.
    assert_close(jq.to_euler(q, "ZYX"), [np.pi / 2, 0, 0], tol=10 * TOL)
    a = jnp.asarray([0.3, -0.2, 0.5], DTYPE)
    # Extrinsic xyz equals intrinsic ZYX with the angles reversed.
    assert_same_rotation(jq.from_euler(a, "xyz"), jq.from_euler(a[::-1], "ZYX"))


def test_unknown_sequence():
    q = jq.identity(dtype=DTYPE)
    for bad in ("xxy", "xyzz", "xYz", "abc", 3, "XyZ"):
        with pytest.raises(ValueError, match="seq"):
            jq.to_euler(q, bad)
        with pytest.raises(ValueError, match="seq"):
            jq.from_euler(jnp.zeros(3, DTYPE), bad)


_DERIVATIVE_SEQUENCES = ["xyz", "ZXZ", "yxz", "XZX"]  # asymmetric and symmetric, extrinsic and intrinsic
_derivatives = {
    s: jax.jit(
        lambda q, t, c, s=s: (
            jax.jvp(lambda x: jq.to_euler(x, s), (q,), (t,))[1],
            jax.vjp(lambda x: jq.to_euler(x, s), q)[1](c)[0],
        )
    )
    for s in _DERIVATIVE_SEQUENCES
}


@pytest.mark.parametrize("seq", _DERIVATIVE_SEQUENCES)
def test_closed_form_derivatives_match_central_differences_of_scipy(seq):
    """``to_euler``'s hand-written JVP against central differences of scipy's ``as_euler`` (float64,
    step 1e-6, an independent formula), along random tangents of 32 random quaternions kept 0.05 rad
    from gimbal lock and from the outer angles' wrap at +-pi; reverse mode is its transpose
    (``<c, J t> = <J^T c, t>``). Measured largest errors: float64 2.0e-9 (the differences' own
    error) and 2.7e-15, float32 7.9e-7 and 1.3e-6; bounds 15x to 37x above them (3e-8 and 1e-13,
    2e-5 and 3e-5)."""
    rng = np.random.default_rng(7)
    q = random_quats(11, n=400, with_singular=False, dtype=np.float64)
    ref = Rotation.from_quat(to_scipy(q)).as_euler(seq)
    symmetric = seq[0].lower() == seq[2].lower()
    middle_gap = np.minimum(ref[:, 1], np.pi - ref[:, 1]) if symmetric else np.pi / 2 - np.abs(ref[:, 1])
    ok = (middle_gap > 0.05) & np.all(np.pi - np.abs(ref[:, [0, 2]]) > 0.05, axis=-1)
    q = q[ok][:32]
    assert q.shape[0] == 32
    t = rng.normal(size=q.shape)
    c = rng.normal(size=(32, 3))
    h = 1e-6

    def scipy_angles(x):
        return Rotation.from_quat(to_scipy(x)).as_euler(seq)

    expected = (scipy_angles(q + h * t) - scipy_angles(q - h * t)) / (2 * h)
    jvp, vjp = _derivatives[seq](*(jnp.asarray(a, DTYPE) for a in (q, t, c)))
    tol, transposed_tol = (3e-8, 1e-13) if DTYPE == jnp.float64 else (2e-5, 3e-5)
    assert_close(jvp, expected, tol=tol, what="jvp")
    lhs = np.sum(c * np.asarray(jvp, np.float64), axis=-1)
    rhs = np.sum(np.asarray(vjp, np.float64) * t, axis=-1)
    assert_close(rhs, lhs, tol=transposed_tol, what="<J^T c, t> against <c, J t>")
