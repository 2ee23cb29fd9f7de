"""Attitude and gyro-bias estimation with the MEKF: a star tracker and a biased gyro.

A spacecraft turns slowly; a rate gyro sampled at 1 Hz has angle random walk and a drifting
bias, and a star tracker reports two star directions every 10 s (between them the filter
propagates on the gyro alone: the missing rows are NaN). The filter starts from QUEST on the
first star-tracker frame, with Shuster's covariance as its prior. The noise values are those of
Crassidis & Junkins' attitude-estimation example: sigma_u = sqrt(10) 1e-10 rad/s^3/2,
sigma_v = sqrt(10) 1e-7 rad/s^1/2, 6 arcsec per star, initial bias 0.1 deg/h per axis.

1. A Monte Carlo of many runs as one call of `jq.mekf` (every argument batched): NEES and NIS
   against their chi-square 95 % bounds, and the fraction of attitude errors inside 3 sigma.
2. The same filter run in a Python loop of `mekf_init`/`mekf_predict`/`mekf_update` steps, for
   the time per step against the batched scan.
3. The three noise parameters learned by gradient descent (optax Adam on their logarithms) on
   the innovations' negative log-likelihood, from a start 10x off each: in a MEMS scenario (10 Hz
   gyro with 1e-3 rad/s^1/2 angle random walk, a vector sensor of 5e-3 rad at every sample),
   since the star tracker's data cannot tell the gyro's noise (it adds 0.2 arcsec between frames).

Saves a figure (attitude error inside its 3-sigma envelope, bias estimate, the fit's path) to
examples/out/star_tracker_mekf.png.

Run: python examples/star_tracker_mekf.py [--runs 200] [--steps 3600] [--fit-steps 150] [--fit-runs 20]
     [--out examples/out]
"""

from __future__ import annotations

import argparse
import functools
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
from scipy.stats import chi2  # noqa: E402

import jaxquat as jq  # noqa: E402

DT = 1.0  # s, gyro sample interval
EVERY = 10  # star tracker: one measurement every 10 gyro samples
SU, SV = np.sqrt(10) * 1e-10, np.sqrt(10) * 1e-7  # rad/s^3/2, rad/s^1/2
SIG = np.radians(6.0 / 3600)  # 6 arcsec
BIAS = np.radians(0.1 / 3600)  # 0.1 deg/h
STARS = jnp.asarray([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])  # reference frame
P0_BIAS = np.radians(0.2 / 3600) ** 2  # prior variance of each bias component, (rad/s)^2
NOISE = dict(vector_noise=SIG, gyro_noise=SV, bias_noise=SU)


@functools.partial(jax.jit, static_argnums=(1, 2))
def synthetic(key, n, sensors=None):
    """One run: truth, gyro record, star-tracker record (NaN rows between measurements), prior.
    ``sensors``: (dt, every, sigma_u, sigma_v, sigma) if not the star-tracker scenario's.

    Every random number of the run comes from one ``jax.random.normal`` call, sliced: each call
    compiles JAX's random-bit hash again, and with five calls (one per noise source, as until
    session 55) this program compiled in 3.0 s against 1.4 s (20 runs of 600 samples, float64,
    one core of this 2-core CPU, the suite's XLA flags); the fast variant of
    ``tests/test_examples.py`` ran in 15.4-16.0 s against 18.6-19.8 s."""
    dt, every, su, sv, sig = sensors or (DT, EVERY, SU, SV, SIG)
    # attitude (4), prior bias (3), bias walk (n x 3 x 2), gyro noise (n x 3), star noise (n x 2 x 3)
    draws = jax.random.normal(key, (7 + 15 * n,))
    g_att, g_x0, g_bias, g_gyro, g_st = jnp.split(draws, np.cumsum([4, 3, 6 * n, 3 * n]))
    t = dt * jnp.arange(n)
    omega = jnp.stack([1e-3 * jnp.sin(0.01 * t), 1e-3 * jnp.cos(0.007 * t), 5e-4 + 0 * t], -1)
    cov = su**2 * jnp.asarray([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    ab = g_bias.reshape(n, 3, 2) @ jnp.linalg.cholesky(cov).T  # bias: interval mean and increment
    bias = BIAS + jnp.concatenate([jnp.zeros((1, 3)), jnp.cumsum(ab[:-1, :, 1], 0)])
    gyro = omega + bias + (ab[..., 0] + sv * jnp.sqrt(dt) * g_gyro.reshape(n, 3)) / dt

    def turn(q, w):
        return jq.plus(q, w * dt), q

    # a uniformly random attitude: a normalised Gaussian 4-vector (as jq.random draws one)
    _, q_true = jax.lax.scan(turn, jq.normalize(g_att), omega)
    body = jq.rotate(jq.conjugate(q_true)[:, None], jnp.broadcast_to(STARS, (n, 2, 3)))
    body = body + sig * g_st.reshape(body.shape)
    body = jnp.where((jnp.arange(n) % every == 0)[:, None, None], body, jnp.nan)
    # The prior: QUEST on the first star-tracker frame, with Shuster's covariance for the attitude
    # block (that frame is then not given to the filter again), and the bias known to P0's spread.
    q0 = jq.quest(body[0], STARS, jnp.full(2, sig**-2.0))
    p_att = jq.attitude_covariance(body[0], sig)
    p0 = jnp.zeros((6, 6)).at[:3, :3].set(p_att).at[3:, 3:].set(P0_BIAS * jnp.eye(3))
    bias0 = bias[0] - jnp.sqrt(P0_BIAS) * g_x0
    return dict(q_true=q_true, bias=bias, gyro=gyro, body=body.at[0].set(jnp.nan), q0=q0, bias0=bias0, P0=p0)


def run_filter(d, dt=DT, **noise):
    return jq.mekf(d["q0"], d["bias0"], d["P0"], dt, d["gyro"], d["body"], STARS[None], **(NOISE | noise))


@jax.jit
def statistics(data, result):
    """Errors (dtheta, dbias), NEES per run and sample, run-averaged NIS per sample, where measured."""
    err = jnp.concatenate([jq.minus(data["q_true"], result.q), data["bias"] - result.bias], -1)
    nees = jnp.einsum("rni,rnij,rnj->rn", err, jnp.linalg.inv(result.P), err)
    has = result.dof > 0
    nis = jnp.where(has, result.nis, 0.0).sum(0) / has.sum(0).clip(1)
    return err, nees, nis, has


def monte_carlo(runs, n):
    data = jax.vmap(synthetic, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), runs), n)
    batched = jax.jit(run_filter)
    t0 = time.perf_counter()
    jax.block_until_ready(batched(data))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = jax.block_until_ready(batched(data))
    run_s = time.perf_counter() - t0
    err, nees, nis, has = statistics(data, result)
    lo, hi = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    inside_nees = float(jnp.mean((nees.mean(0) > lo) & (nees.mean(0) < hi)))
    measured = has[0]
    inside_nis = float(jnp.mean(((nis > lo) & (nis < hi))[measured]))
    sigma = jnp.sqrt(jnp.diagonal(result.P, axis1=-2, axis2=-1))
    in3 = float(jnp.mean(jnp.abs(err[..., :3]) < 3 * sigma[..., :3]))
    one = jax.tree.map(lambda x: x[0], data)
    single = jax.jit(run_filter)
    jax.block_until_ready(single(one))
    t0 = time.perf_counter()
    jax.block_until_ready(single(one))
    single_s = time.perf_counter() - t0
    print(
        f"Monte Carlo: {runs} runs x {n} samples in one call: {run_s:.3f} s "
        f"({1e6 * run_s / (runs * n):.2f} us per filter step; compile {compile_s:.1f} s); "
        f"one run alone {1e6 * single_s / n:.2f} us per step"
    )
    print(f"average NEES {float(nees.mean()):.3f} (6 dof), inside its 95% bounds at {inside_nees:.3f} of the times")
    print(
        f"average NIS {float(nis[measured].mean()):.3f} (6 dof), inside its 95% bounds at {inside_nis:.3f} of "
        "the updates"
    )
    print(f"attitude errors inside 3 sigma: {in3:.4f}")
    final = np.degrees(np.asarray(sigma[0, -1, :3])) * 3600
    print(
        f"steady-state 3-sigma attitude bound {3 * final.max():.2f} arcsec; "
        f"RMS error {np.degrees(float(jnp.sqrt(jnp.mean(err[:, n // 2 :, :3] ** 2)))) * 3600:.2f} arcsec per axis"
    )
    return one, jax.tree.map(lambda x: x[0], result)


def python_loop(d, n):
    """The same filter as a Python loop of jitted init/predict/update calls (what a filter written
    step by step costs), per step."""
    predict = jax.jit(lambda s, g: jq.mekf_predict(s, g, DT, gyro_noise=SV, bias_noise=SU))
    update = jax.jit(lambda s, b: jq.mekf_update(s, b, STARS, vector_noise=SIG)[0])
    state = jq.mekf_init(d["q0"], d["bias0"], d["P0"])
    state = update(state, d["body"][0])
    jax.block_until_ready(predict(state, d["gyro"][0]))
    t0 = time.perf_counter()
    for k in range(1, n):
        state = update(predict(state, d["gyro"][k - 1]), d["body"][k])
    jax.block_until_ready(state)
    return (time.perf_counter() - t0) / (n - 1)


# The learning scenario: with the star tracker above, the gyro's noise adds 0.2 arcsec between
# frames against the tracker's 6, so no data can tell its value (the likelihood is flat in it).
# A MEMS gyro and a 10 Hz vector sensor (sun sensor or magnetometer grade) make all three count.
MEMS = (0.1, 1, 1e-5, 1e-3, 5e-3)  # dt, every, sigma_u, sigma_v, sigma


def fit_noise(runs, n, steps):
    """Adam on the log of the three noise parameters: the innovations' negative log-likelihood of
    ``runs`` records of the MEMS scenario (one vmapped call per step), from a start 10x off."""
    data = jax.vmap(synthetic, in_axes=(0, None, None))(jax.random.split(jax.random.PRNGKey(1), runs), n, MEMS)
    truth = jnp.log(jnp.asarray(MEMS[2:]))[jnp.asarray([1, 0, 2])]  # (sigma_v, sigma_u, sigma)
    start = truth + jnp.log(jnp.asarray([10.0, 0.1, 10.0]))

    def nll(x):
        sv, su, sig = jnp.exp(x)
        result = run_filter(data, MEMS[0], gyro_noise=sv, bias_noise=su, vector_noise=sig)
        return -jnp.sum(result.log_likelihood) / runs

    opt = optax.adam(0.1)

    @jax.jit
    def step(x, state):  # one compiled function serves the fit and the value at the truth
        value, g = jax.value_and_grad(nll)(x)
        updates, state = opt.update(g, state)
        return optax.apply_updates(x, updates), state, value

    x, state, path = start, opt.init(start), []
    for _ in range(steps):
        x, state, value = step(x, state)
        path.append(float(value))
    ratio = np.exp(np.asarray(x - truth))
    print(
        f"noise fit by gradient ({steps} Adam steps from 10x, 0.1x, 10x; {runs} MEMS records of {n}): learned / true = "
        f"gyro {ratio[0]:.3f}, bias {ratio[1]:.3f}, vector sensor {ratio[2]:.3f}; "
        f"NLL {path[0]:.1f} -> {path[-1]:.1f} (at the true values {float(step(truth, state)[2]):.1f})"
    )
    return path


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--steps", type=int, default=3600)
    ap.add_argument("--fit-steps", type=int, default=150)
    ap.add_argument("--fit-runs", type=int, default=20)
    ap.add_argument("--out", default="examples/out")
    opts = ap.parse_args(argv)
    d, r = monte_carlo(opts.runs, opts.steps)
    per_step = python_loop(d, min(opts.steps, 500))
    print(f"Python loop of jitted predict/update: {1e6 * per_step:.1f} us per step")
    path = fit_noise(opts.fit_runs, 600, opts.fit_steps)

    out = pathlib.Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = DT * np.arange(opts.steps) / 60
    arcsec = np.degrees(1.0) * 3600
    err = np.asarray(jq.minus(d["q_true"], r.q)) * arcsec
    sigma = np.sqrt(np.diagonal(np.asarray(r.P), axis1=-2, axis2=-1)) * arcsec
    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for i, name in enumerate("xyz"):
        axes[0, 0].plot(t, err[:, i], lw=0.6, label=f"{name} error")
    axes[0, 0].plot(t, 3 * sigma[:, 0], "k", lw=0.8, label="+-3 sigma (x)")
    axes[0, 0].plot(t, -3 * sigma[:, 0], "k", lw=0.8)
    axes[0, 0].set_ylim(-5 * sigma[opts.steps // 10, 0], 5 * sigma[opts.steps // 10, 0])
    axes[0, 0].set_ylabel("attitude error, arcsec")
    axes[0, 0].legend(fontsize=7)
    deg_h = np.degrees(1.0) * 3600
    axes[0, 1].plot(t, np.asarray(r.bias) * deg_h, lw=0.8)
    axes[0, 1].plot(t, np.asarray(d["bias"]) * deg_h, "k--", lw=0.6)
    axes[0, 1].set_ylabel("gyro bias, deg/h (dashed: truth)")
    axes[1, 0].semilogy(t, 3 * sigma[:, :3])
    axes[1, 0].set_ylabel("3 sigma attitude, arcsec")
    for ax in (axes[0, 0], axes[0, 1], axes[1, 0]):
        ax.set_xlabel("t, min")
    axes[1, 1].plot(path)
    axes[1, 1].set_xlabel("Adam step")
    axes[1, 1].set_ylabel("noise fit (MEMS case): -log likelihood")
    fig.suptitle("MEKF: star tracker every 10 s, biased gyro at 1 Hz")
    fig.tight_layout()
    fig.savefig(out / "star_tracker_mekf.png", dpi=110)
    print(f"figure: {out / 'star_tracker_mekf.png'}")


if __name__ == "__main__":
    main()
