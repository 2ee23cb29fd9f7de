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
    """Middle angle at, and within 1e-4 degrees of, the singular value; float32 too."""
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
    out = _to[seq](q)
    assert np.all(np.isfinite(np.asarray(out)))
    back = _from[seq](out)
    # Rotation reproduced to rounding: 1e-4 degrees is far larger than this tolerance.
    assert_same_rotation(back, q, tol=20 * TOL)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = Rotation.from_quat(to_scipy(q)).as_euler(seq)
    assert_close(np.asarray(out)[:, 1], ref[:, 1], tol=1e-3)
    # Gradients are finite at gimbal lock.
    g = jax.jacrev(lambda x: jq.to_euler(x, seq))(q[0])
    assert np.all(np.isfinite(np.asarray(g)))


@given(seeds)
def test_euler_round_trip_property(seed):
    rng = np.random.default_rng(seed)
    seq = SEQUENCES[seed % 24]
    q = random_quats(seed)
    assert_same_rotation(_from[seq](_to[seq](q)), q, tol=20 * TOL)
    # Angles drawn inside the principal ranges come back unchanged.
    symmetric = seq[0].lower() == seq[2].lower()
    mid = rng.uniform(0.1, np.pi - 0.1, 16) if symmetric else rng.uniform(-1.4, 1.4, 16)
    angles = np.stack([rng.uniform(-3.0, 3.0, 16), mid, rng.uniform(-3.0, 3.0, 16)], -1).astype(DTYPE)
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
