"""The optimisation examples run as documented (fast variants) and their printed claims hold.

A file of their own so that pytest-xdist (``--dist loadfile``) runs them beside the
other examples (``test_examples.py``) rather than after them.

Each runs once per `make test`, in the test worker's own process
(``helpers.run_example_in_process``): the two that switch float64 on in the float64 pass,
``learned_controller`` (JAX's default float32) in the float32 pass (in a float64 subprocess it
took 25 s; the float32 pass is the shorter one)."""

from __future__ import annotations

import re

import pytest

from helpers import X64, run_example_in_process

FLOAT64 = pytest.mark.skipif(not X64, reason="examples run in float64 by design; once per make test")


@FLOAT64
def test_min_energy_slew_example(tmp_path):
    text = run_example_in_process(
        "examples/min_energy_slew.py", "--outer", "4", "--inner", "30", "--steps", "100", "--out", str(tmp_path)
    )
    excess = float(re.search(r"optimum 12 theta\^2 / T\^3 = [\d.]+: ([+-][\d.]+) %", text).group(1))
    assert abs(excess) < 0.5, text  # the target: within 0.5 % of the analytic optimum
    att, rate = (
        float(x)
        for x in re.search(r"terminal attitude error ([\d.e+-]+) rad, terminal rate ([\d.e+-]+)", text).groups()
    )
    assert att < 1e-4 and rate < 1e-4, text
    assert (tmp_path / "min_energy_slew.png").stat().st_size > 10_000


@FLOAT64
def test_inertia_identification_example(tmp_path):
    text = run_example_in_process("examples/inertia_identification.py", "--noise", "1e-2", "--out", str(tmp_path))
    err = float(re.search(r"noise 1e-02 rad: relative tensor error ([\d.e+-]+)", text).group(1))
    assert err < 5e-3, text  # measured 5.4e-4; the error scales with the noise (4.8e-5 at 1e-3)
    assert (tmp_path / "inertia_identification.png").stat().st_size > 10_000


@pytest.mark.skipif(X64, reason="the example runs in JAX's default float32: in the float32 pass, once per make test")
def test_learned_controller_example(tmp_path):
    text = run_example_in_process(
        "examples/learned_controller.py",
        "--steps",
        "6",
        "--batch",
        "16",
        "--bodies",
        "64",
        "--no-progress",
        "--out",
        str(tmp_path),
    )
    before = float(re.search(r"untrained: success rate [\d.]+ %, mean cost ([\d.]+)", text).group(1))
    after = float(
        re.search(r"trained \(6 Adam steps, batch 16\): success rate [\d.]+ %, mean cost ([\d.]+)", text).group(1)
    )
    assert after < 0.9 * before, text  # training through the batched simulation lowers the cost
    assert (tmp_path / "learned_controller.png").stat().st_size > 10_000
