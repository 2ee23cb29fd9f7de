"""The README's quick tour runs exactly as written."""

import pathlib
import re

import jax


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


def test_import_changes_no_global_setting():
    import subprocess
    import sys

    code = "import jax; before = jax.config.jax_enable_x64; import jaxquat; assert jax.config.jax_enable_x64 == before; print(before)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
