"""The suite's deep frame (``tests/frames.py``) calls what it is given and nothing else."""

from __future__ import annotations

import subprocess
import sys

import pytest
from frames import deep_frame, script_in_deep_frame


def _depth(n: int) -> int:
    return 0 if n == 0 else 1 + _depth(n - 1)


def test_deep_frame_returns_the_call_s_result_and_passes_its_arguments():
    assert deep_frame(divmod, 17, 5) == (3, 2)
    assert deep_frame(sorted, [3, 1, 2], reverse=True) == [3, 2, 1]
    assert deep_frame(_depth, 500) == 500  # a stack of 500 frames above it


def test_deep_frame_lets_an_exception_through():
    with pytest.raises(ZeroDivisionError):
        deep_frame(divmod, 1, 0)


def test_a_script_runs_as_main_from_the_deep_frame():
    script = "import sys\ndef f():\n    return __name__\nprint(f(), sys._getframe(1).f_code.co_stacksize)\n"
    out = subprocess.run([sys.executable, "-c", script_in_deep_frame(script)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    name, stacksize = out.stdout.split()
    assert name == "__main__"
    assert int(stacksize) >= 100_000  # the frame below the script's is the deep one
