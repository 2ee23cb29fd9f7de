"""The examples run as documented (fast variants) and their printed claims hold.

They switch float64 on themselves, so they run in subprocesses, once per `make test`
(in the float64 pass)."""

from __future__ import annotations

import pathlib
import re
import subprocess
import sys

import pytest

from helpers import X64

ROOT = pathlib.Path(__file__).parent.parent
pytestmark = pytest.mark.skipif(not X64, reason="examples run in float64 by design; once per make test")


def _run(*args: str) -> str:
    out = subprocess.run([sys.executable, *args], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_fit_rotation_example():
    text = _run("examples/fit_rotation.py", "--iters", "500")
    rows = {m.group(1).strip(): m.groups()[1:] for m in re.finditer(r"^(\w+, lr [\d.]+)\s+(\S+)\s+(\S+)\s+(\S+)$", text, re.M)}
    tangent = rows["tangent, lr 0.1"]
    assert int(tangent[0]) < 500, text  # reaches 1e-8 rad
    assert float(tangent[2]) < 1e-13, text  # |q| stays 1 without renormalisation
    assert set(rows) == {"tangent, lr 0.1", "naive, lr 0.1", "naive, lr 0.05"}


def test_spline_plot_example(tmp_path):
    text = _run("examples/spline_plot.py", "--out", str(tmp_path))
    assert (tmp_path / "rotation_spline.png").stat().st_size > 10_000
    jumps = [float(x) for x in re.findall(r"([\d.]+e[-+]\d+) rad/s", text)]
    assert len(jumps) == 2 and max(jumps) < 1e-5, text


def test_dzhanibekov_example(tmp_path):
    text = _run("examples/dzhanibekov.py", "--t-end", "20", "--out", str(tmp_path))
    rel = float(re.search(r"relative difference ([\d.e+-]+)", text).group(1))
    assert rel < 1e-6, text  # measured flip interval vs 2 K(m) / lambda
    rk = float(re.search(r"max attitude difference ([\d.e+-]+) rad", text).group(1))
    assert rk < 1e-6, text  # RKMK45 at rtol 1e-10 tracks the exact solution
    assert (tmp_path / "dzhanibekov.png").stat().st_size > 10_000


def test_min_energy_slew_example(tmp_path):
    text = _run("examples/min_energy_slew.py", "--outer", "4", "--inner", "30", "--steps", "100", "--out", str(tmp_path))
    excess = float(re.search(r"optimum 12 theta\^2 / T\^3 = [\d.]+: ([+-][\d.]+) %", text).group(1))
    assert abs(excess) < 0.5, text  # the target: within 0.5 % of the analytic optimum
    att, rate = (float(x) for x in re.search(r"terminal attitude error ([\d.e+-]+) rad, terminal rate ([\d.e+-]+)", text).groups())
    assert att < 1e-4 and rate < 1e-4, text
    assert (tmp_path / "min_energy_slew.png").stat().st_size > 10_000


def test_inertia_identification_example(tmp_path):
    text = _run("examples/inertia_identification.py", "--noise", "1e-2", "--out", str(tmp_path))
    err = float(re.search(r"noise 1e-02 rad: relative tensor error ([\d.e+-]+)", text).group(1))
    assert err < 5e-3, text  # measured 5.4e-4; the error scales with the noise (4.8e-5 at 1e-3)
    assert (tmp_path / "inertia_identification.png").stat().st_size > 10_000


def test_time_optimal_reorientation_example(tmp_path):
    text = _run("examples/time_optimal_reorientation.py", "--intervals", "10", "--levels", "1", "--starts", "4",
                "--outer", "6", "--inner", "80", "--no-progress", "--out", str(tmp_path))
    lines = text.strip().splitlines()
    assert lines[-1].startswith("minimum time: ") and lines[-2].startswith("terminal constraint violation: "), text
    time = float(lines[-1].split(": ")[1])
    assert time < 2 * (3.14159265358979 ** 0.5) * 0.98, text  # beats the eigenaxis bang-bang time 2 sqrt(pi)
    assert float(lines[-2].split(": ")[1]) < 1e-5, text
    saturated = int(re.search(r"^\s+10\s+\S+\s+\S+\s+(\d+) %$", text, re.M).group(1))
    assert saturated > 70, text  # bang-bang: most torque values at the bound
    assert (tmp_path / "time_optimal_reorientation.png").stat().st_size > 10_000


def test_learned_controller_example(tmp_path):
    text = _run("examples/learned_controller.py", "--steps", "6", "--batch", "16", "--bodies", "64",
                "--no-progress", "--out", str(tmp_path))
    before = float(re.search(r"untrained: success rate [\d.]+ %, mean cost ([\d.]+)", text).group(1))
    after = float(re.search(r"trained \(6 Adam steps, batch 16\): success rate [\d.]+ %, mean cost ([\d.]+)", text).group(1))
    assert after < 0.9 * before, text  # training through the batched simulation lowers the cost
    assert (tmp_path / "learned_controller.png").stat().st_size > 10_000
