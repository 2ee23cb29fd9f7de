"""The README's quick tour runs exactly as written."""

import pathlib
import re

import jax
import pytest
from helpers import X64


def test_quick_tour_runs(capsys):
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    block = re.search(r"## Quick tour\n\n```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(block, "README quick tour", "exec"), namespace)
    J = namespace["J"]
    assert J.shape == (3, 4)
    assert float(abs(J[:, 1:] - 2 * jax.numpy.eye(3)).max()) == 0.0
    assert namespace["angles"].shape == (1000, 3)
    assert "nan" not in capsys.readouterr().out.lower()


def test_dynamics_example_runs_and_its_claims_hold(capsys):
    text = (pathlib.Path(__file__).parent.parent / "README.md").read_text()
    block = re.search(r"## Kinematics and dynamics\n.*?```python\n(.*?)```", text, re.S).group(1)
    ns = {}
    exec(compile(block, "README dynamics example", "exec"), ns)
    tol = 1e-10 if jax.config.jax_enable_x64 else 1e-5
    assert float(abs(ns["same"] - ns["qdd"]).max()) < tol
    assert float(abs(ns["alpha"] - ns["euler"]).max()) < tol
    assert ns["grad"].shape == (3, 3) and bool(jax.numpy.all(jax.numpy.isfinite(ns["grad"])))
    assert "nan" not in capsys.readouterr().out.lower()


@pytest.mark.skipif(not X64, reason="once per make test: its subprocess sets no dtype, the same run in both passes")
def test_import_changes_no_global_setting():
    import subprocess
    import sys

    code = (
        "import jax; before = jax.config.jax_enable_x64; import jaxquat; "
        "assert jax.config.jax_enable_x64 == before; print(before)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
