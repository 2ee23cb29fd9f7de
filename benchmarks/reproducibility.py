"""Does minimum_time_reorientation give the same answer on any x86-64 CPU and core count?

Runs the test suite's two 10-interval problems (tests/test_time_optimal.py: the asymmetric body,
1.2 rad with ``omegaf = (0, 0, 0.2)``, and Bilimoria & Wie's 180 degrees with J = I) in fresh
processes under XLA flags that change the code XLA generates (the vector ISA, the CPU emitters)
or the parallelism (one intra-op thread, 2 and 4 host devices, one core by ``taskset``), and
prints every time to 17 digits and the largest relative spread per solver. The default
(interior point, 8 starts) and, with ``--single-shooting``, the augmented-Lagrangian L-BFGS
solver (the suite's FAST settings), whose local optimum can depend on the ISA.

Run: python benchmarks/reproducibility.py [--single-shooting]   (a few minutes; CPU only)
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys

CONFIGS = [
    ("default", "", []),
    ("AVX2", "--xla_cpu_max_isa=AVX2", []),
    ("SSE4_2", "--xla_cpu_max_isa=SSE4_2", []),
    ("legacy emitters", "--xla_cpu_use_fusion_emitters=false", []),
    ("1 thread", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1", []),
    ("2 devices", "--xla_force_host_platform_device_count=2", []),
    ("4 devices", "--xla_force_host_platform_device_count=4", []),
    ("taskset -c 0", "", ["taskset", "-c", "0"]),
]

CHILD = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import jaxquat as jq
inertia = np.array([[1.2, 0.1, 0.0], [0.1, 1.0, -0.05], [0.0, -0.05, 0.8]])
bound = np.array([1.0, 0.8, 0.6])
q0 = np.array([1.0, 0.0, 0.0, 0.0])
qf = np.array([np.cos(0.6), 0.0, np.sin(0.6) * 0.6, np.sin(0.6) * 0.8])
wf = np.array([0.0, 0.0, 0.2])
options = {"intervals": 10}
if sys.argv[1] == "single_shooting":
    options.update(starts=4, outer=6, inner=80, method="single_shooting")
out = {
    "asymmetric": float(jq.minimum_time_reorientation(inertia, bound, q0, qf, omegaf=wf, **options).time),
    "bilimoria-wie": float(jq.minimum_time_reorientation(np.eye(3), np.ones(3), q0, [0.0, 1, 0, 0], **options).time),
}
print(json.dumps(out))
"""


def _legacy() -> bool:
    """Whether XLA still has its elemental CPU emitters' flag (jaxlib 0.11.2 aborts on it)."""
    from importlib.metadata import version

    return tuple(int(x) for x in version("jaxlib").split(".")[:2]) < (0, 11)


def run(method: str, flags: str, prefix: list[str]) -> dict:
    env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + flags).strip())
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # each configuration compiles its own code
    out = subprocess.run(
        [*prefix, sys.executable, "-c", CHILD, method], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--single-shooting", action="store_true", help="also the single-shooting solver")
    args = ap.parse_args()
    methods = ["interior_point"] + (["single_shooting"] if args.single_shooting else [])
    configs = [c for c in CONFIGS if (not c[2] or shutil.which(c[2][0])) and (c[0] != "legacy emitters" or _legacy())]
    for method in methods:
        print(f"\n{method}: time of each problem per configuration")
        rows = {name: run(method, flags, prefix) for name, flags, prefix in configs}
        for name, r in rows.items():
            print(f"  {name:16s} " + "  ".join(f"{k} {v:.17g}" for k, v in r.items()))
        for key in next(iter(rows.values())):
            values = [r[key] for r in rows.values()]
            print(f"  {key}: largest relative spread {(max(values) - min(values)) / min(values):.2g}")


if __name__ == "__main__":
    main()
