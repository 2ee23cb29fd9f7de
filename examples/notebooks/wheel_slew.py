# ---
# jupyter:
#   jupytext:
#     cell_metadata_filter: -all
#     notebook_metadata_filter: kernelspec
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.17.3
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # A reaction-wheel slew that keeps the star tracker out of the Sun
#
# A spacecraft (inertia `J`, without the wheels' axial inertias) turns by three reaction
# wheels on its body axes. With no external torque its total angular momentum
# `R(q) (J w + A h)` stays zero, and the gyrostat equations are
# `J w' = -A u - w x (J w + A h)` and `h' = u`, with `u` the wheel motor torques and `h`
# the wheel momenta.
#
# The slew is 90 degrees about z. On the eigenaxis path the star tracker's boresight (body
# x) would sweep through the Sun. The limits hold at every integration step, not only at
# the nodes:
#
# - wheel torque `|u_i| <= 0.1` N m;
# - wheel momentum `|h_i| <= 0.12` N m s (the wheel speed);
# - body rate `|w_i| <= 0.15` rad/s;
# - boresight at least 20 degrees from the Sun.
#
# We solve it twice, by direct multiple shooting and a primal-dual interior point: first in
# least time, then in least fuel (`int |u|_1`) for 1.5 times that time. The `assert`s make
# this notebook a test: the suite executes it.

# %%
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import jaxquat as jq

sys.path.insert(0, "..")  # the example's geometry, re-simulation and figure
from sun_avoidance import BORESIGHT, HALF, Q0, QF, SUN
from wheel_slew import INERTIA, figure, report, resimulate

wheels = jq.ReactionWheels(np.eye(3), 0.1, momentum_limit=0.12)  # spin axes (rows), torque and momentum limits
constraints = dict(rate_bound=0.15, keep_out=[(BORESIGHT, SUN, HALF)], wheels=wheels)
N = 12  # shooting intervals (the example's default is 16)
print(f"Sun {SUN}, cone half-angle {np.degrees(HALF):.0f} deg about it; boresight {BORESIGHT} in the body")

# %% [markdown]
# ## Least time
#
# `minimum_time_reorientation` takes the wheels in place of a body torque bound (`None`).
# The first call compiles the solver (tens of seconds); the solve itself takes seconds.

# %%
fast = jq.minimum_time_reorientation(INERTIA, None, Q0, QF, intervals=N, **constraints)
print(f"converged {bool(fast.converged)}: {float(fast.time):.6f} s in {int(fast.iterations)} iterations")
print("wheel momenta", fast.wheel_momentum.shape, "wheel torques", fast.controls.shape)
assert bool(fast.converged) and float(fast.violation) < 1e-9

# %% [markdown]
# ## Least fuel in 1.5 times that time
#
# Fuel is `int sum_i |u_i| dt`. With time to spare, the wheels push in short pulses and coast
# in between (here most of the held torques are zero), and the boresight now grazes the cone.

# %%
fuel = jq.minimum_fuel_reorientation(INERTIA, Q0, QF, 1.5 * float(fast.time), intervals=N, **constraints)
u = np.asarray(fuel.controls)
coast = np.mean(np.abs(u) < 1e-3 * 0.1)
print(f"converged {bool(fuel.converged)}: fuel {float(fuel.cost):.6f} N m s; {100 * coast:.0f} % of the torques coast")
fuel_fast = float(fast.time) / N * np.abs(np.asarray(fast.controls)).sum()
print(f"the least-time slew spends {fuel_fast:.6f} N m s")
assert bool(fuel.converged) and float(fuel.cost) < fuel_fast and coast > 0.5

# %% [markdown]
# ## Every limit, checked on a finer re-simulation
#
# The returned wheel torques, held on each interval, drive `jq.ReactionWheelSpacecraft`'s own
# vector field at 10 times finer steps (40 RKMK4 steps per interval against the solver's 4).

# %%
paths = []
for name, r in (("least time", fast), ("least fuel", fuel)):
    ys, drift = resimulate(r, 40)
    boresight = report(name, r, ys, drift)
    sun_angle = np.degrees(np.arccos(np.clip(boresight @ SUN, -1, 1)))
    assert sun_angle.min() >= np.degrees(HALF) - 1e-2
    assert np.abs(ys["w"]).max() <= 0.15 * (1 + 1e-4) and np.abs(ys["h"]).max() <= 0.12 * (1 + 1e-4)
    assert np.abs(np.asarray(r.controls)).max() <= 0.1 * (1 + 1e-8) and drift < 1e-12
    error = np.linalg.norm(np.asarray(jq.minus(jnp.asarray(ys["q"][-1]), jnp.asarray(QF))))
    assert error < 1e-4  # the solver's 4 steps per interval against 40: the same slew
    paths.append((name, r, ys, boresight))

# %% [markdown]
# Left: the boresight on the sky, with the keep-out cone and the eigenaxis path through it.
# Then the wheel torques, the body rates and the wheel momenta against their limits (dashed).
# In least time all three limits bind in turn.

# %%
import matplotlib.pyplot as plt

fig = figure(paths)
plt.show()
