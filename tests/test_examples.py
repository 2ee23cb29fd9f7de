"""The examples run as documented (fast variants) and their printed claims hold.

They switch float64 on themselves, so they run in subprocesses, once per `make test`
(in the float64 pass)."""

from __future__ import annotations

import re

import pytest

from helpers import X64, run_example

pytestmark = pytest.mark.skipif(not X64, reason="examples run in float64 by design; once per make test")


def test_fit_rotation_example():
    text = run_example("examples/fit_rotation.py", "--iters", "500")
    rows = {m.group(1).strip(): m.groups()[1:] for m in re.finditer(r"^(\w+, lr [\d.]+)\s+(\S+)\s+(\S+)\s+(\S+)$", text, re.M)}
    tangent = rows["tangent, lr 0.1"]
    assert int(tangent[0]) < 500, text  # reaches 1e-8 rad
    assert float(tangent[2]) < 1e-13, text  # |q| stays 1 without renormalisation
    assert set(rows) == {"tangent, lr 0.1", "naive, lr 0.1", "naive, lr 0.05"}


def test_spline_plot_example(tmp_path):
    text = run_example("examples/spline_plot.py", "--out", str(tmp_path))
    assert (tmp_path / "rotation_spline.png").stat().st_size > 10_000
    jumps = [float(x) for x in re.findall(r"([\d.]+e[-+]\d+) rad/s", text)]
    assert len(jumps) == 2 and max(jumps) < 1e-5, text


def test_dzhanibekov_example(tmp_path):
    text = run_example("examples/dzhanibekov.py", "--t-end", "20", "--out", str(tmp_path))
    rel = float(re.search(r"relative difference ([\d.e+-]+)", text).group(1))
    assert rel < 1e-6, text  # measured flip interval vs 2 K(m) / lambda
    rk = float(re.search(r"max attitude difference ([\d.e+-]+) rad", text).group(1))
    assert rk < 1e-6, text  # RKMK45 at rtol 1e-10 tracks the exact solution
    assert (tmp_path / "dzhanibekov.png").stat().st_size > 10_000
