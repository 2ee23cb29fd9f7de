"""The docs name real things: every test and function that docs/equations.md cites exists."""

import pathlib
import re

import pytest

import jaxquat as jq
from helpers import X64

ROOT = pathlib.Path(__file__).parent.parent


def _defined_tests() -> set[str]:
    names = set()
    for path in (ROOT / "tests").glob("test_*.py"):
        names |= set(re.findall(r"^def (test_\w+)", path.read_text(), re.M))
    return names


def _package_modules() -> dict[str, pathlib.Path]:
    """Every module of the package by its name (names are unique across the subpackages), the
    subpackages' ``__init__`` files aside."""
    paths = [p for p in (ROOT / "jaxquat").rglob("*.py") if p.name != "__init__.py"]
    modules = {p.stem: p for p in paths}
    assert len(modules) == len(paths), "two modules of the package share a name"
    return modules


def _module_imports(src: str) -> set[str]:
    """The jaxquat modules a package module's source imports, by name: ``from .m import ...``,
    ``from ..layer.m import ...``, ``from . import m, ...`` and ``from ..[layer] import m, ...``."""
    layers = {p.name for p in (ROOT / "jaxquat").iterdir() if (p / "__init__.py").exists()}
    imported = set()
    for path, names in re.findall(r"^from \.+([\w.]*) import ([\w, ]+|\()", src, re.M):
        if path in ("", *layers):  # ``from . import m`` or ``from ..layer import m, n``
            imported |= {n.strip() for n in names.split(",")}
        else:  # ``from .m import x`` or ``from ..layer.m import (``
            imported.add(path.split(".")[-1])
    return imported


def test_equations_page_cites_existing_tests_and_functions():
    text = (ROOT / "docs" / "equations.md").read_text()
    cited_tests = set(re.findall(r"`(test_\w+)`", text))
    assert len(cited_tests) >= 30
    missing = cited_tests - _defined_tests()
    assert not missing, f"docs/equations.md cites tests that do not exist: {sorted(missing)}"
    cited_functions = {
        name
        for cell in re.findall(r"\| `([a-z_]+)`", text) + re.findall(r", `([a-z_]+)`", text)
        for name in [cell]
        if not name.startswith("test_")
        and name not in {"inertia", "omega", "alpha", "torque", "q", "kin", "dyn", "inr", "trq", "err", "con", "tfree"}
    }
    unknown = {n for n in cited_functions if not hasattr(jq, n)}
    assert not unknown, f"docs/equations.md cites functions jaxquat does not export: {sorted(unknown)}"
    # every public function of the kinematics/dynamics layer appears on the page
    mech = jq.mechanics
    layer = (
        set(mech.kinematics.__all__)
        | set(mech.dynamics.__all__)
        | set(mech.inertia.__all__)
        | set(mech.torques.__all__)
    )
    absent = {n for n in layer if f"`{n}" not in text}
    assert not absent, f"public functions missing from docs/equations.md: {sorted(absent)}"


def test_imports_point_down_the_layer_map_of_architecture_md():
    """Each module imports only modules listed below it in docs/architecture.md (no cycles)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = text.split("```\n")[1]
    paths = re.findall(r"^([\w/]+)\.py", block, re.M)  # top of the map first, as jaxquat/ paths
    modules = {str(p.relative_to(ROOT / "jaxquat").with_suffix("")) for p in _package_modules().values()}
    assert set(paths) == modules, f"architecture.md map != package modules: {set(paths) ^ modules}"
    order = [path.split("/")[-1] for path in paths]
    rank = {m: i for i, m in enumerate(order)}
    for m in order:
        imported = _module_imports(_package_modules()[m].read_text())
        upward = {i for i in imported if rank[i] <= rank[m]}
        assert not upward, f"{m}.py imports {upward}, which the map places above it"


def test_the_module_map_lists_each_module_s_imports():
    """The parenthesis closing each entry of docs/architecture.md's map is the set of jaxquat
    modules that module imports (``_checks`` aside), so the map cannot drift from the code."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = text.split("```\n")[1]
    for entry in re.split(r"^(?=[\w/]+\.py)", block, flags=re.M):
        name = re.match(r"(?:\w+/)?(\w+)\.py", entry)
        if name is None:
            continue
        listed = re.search(r"\(([^()]*)\)\s*$", entry.rstrip()).group(1)
        listed = set() if listed == "none" else {x.strip() for x in listed.split(",")}
        imported = _module_imports(_package_modules()[name.group(1)].read_text())
        assert listed == imported - {"_checks"}, f"{name.group(1)}.py: map lists {listed}, imports {imported}"


def test_the_package_re_exports_every_module_name_by_name():
    """``jaxquat/__init__.pyi`` lists its re-exports explicitly (``name as name``, for type
    checkers and the lazy loader); they must be exactly the modules' own ``__all__``, no name
    twice or missing."""
    import importlib

    text = (ROOT / "jaxquat" / "__init__.pyi").read_text()
    modules = re.findall(r"^from \.([\w.]+) import \(", text, re.M)
    exported = [name for m in modules for name in importlib.import_module(f"jaxquat.{m}").__all__]
    assert len(exported) == len(set(exported))
    assert sorted(jq.__all__) == sorted(exported)
    for m in modules:
        block = text[text.index(f"from .{m} import (") :]
        block = block[: block.index(")")]
        assert set(re.findall(r"(\w+) as (\w+)", block)) == {
            (n, n) for n in importlib.import_module(f"jaxquat.{m}").__all__
        }, m
    assert all(hasattr(jq, name) for name in jq.__all__)


@pytest.mark.skipif(not X64, reason="once per make test: which modules load does not depend on the dtype")
def test_import_jaxquat_imports_a_module_on_first_use_of_its_names():
    """``import jaxquat`` imports none of its modules (``lazy_loader``): the rotations do not
    import diffrax, equinox or optax, nor does ``simulate`` on its default torque-free path (the
    closed form; their import took 0.35 s of a first call); its numerical paths and the solvers
    do. In a fresh interpreter."""
    import subprocess
    import sys

    heavy = "print(sorted(m for m in ('diffrax', 'equinox', 'optax', 'optimistix') if m in sys.modules))\n"
    code = (
        "import sys, numpy as np, jaxquat as jq\n"
        "print(sorted(m for m in sys.modules if m.startswith('jaxquat.')))\n"
        "jq.multiply, jq.to_rotvec, jq.slerp, jq.mekf\n"
        f"{heavy}"
        "sim = jq.simulate(np.array([1.0, 0, 0, 0]), np.array([0.1, 1.0, 0.2]), np.diag([1.0, 2.0, 3.0]), [0.0, 1.0])\n"
        f"{heavy}"
        "jq.RKMK4\n"
        "print('diffrax' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split("\n")[:4] == ["[]", "[]", "[]", "True"], out


def test_no_module_imports_another_module_s_private_names():
    """An underscore means "only used in this module": the kernels the modules share live in the
    private modules (``_quaternion``, ``_rotation``, ``_rates``, ``_arrays``, ...) under plain
    names, so no ``from .module import _name`` crosses a module boundary, in the package or in
    the examples and benchmarks."""
    offenders = []
    for folder in ("jaxquat", "examples", "benchmarks"):
        for path in (ROOT / folder).rglob("*.py"):
            src = path.read_text()
            for names in re.findall(r"^from (?:\.+|jaxquat\.)(?:\w+\.)*\w+ import (\([^)]*\)|[^\n]*)", src, re.M):
                private = [n.strip() for n in names.strip("()").split(",") if n.strip().startswith("_")]
                offenders += [f"{path.relative_to(ROOT)}: {n}" for n in private]
    assert not offenders, offenders


def test_the_api_reference_covers_every_public_module():
    """docs/api/*.md (built by ``make docs``, mkdocstrings) renders each module that
    ``jaxquat/__init__.pyi`` re-exports, once, and mkdocs.yml's nav lists every page."""
    text = (ROOT / "jaxquat" / "__init__.pyi").read_text()
    modules = set(re.findall(r"^from \.([\w.]+) import \(", text, re.M))
    pages = sorted((ROOT / "docs" / "api").glob("*.md"))
    rendered = [m for page in pages for m in re.findall(r"^::: jaxquat\.([\w.]+)$", page.read_text(), re.M)]
    assert sorted(rendered) == sorted(modules), set(rendered) ^ modules
    nav = (ROOT / "mkdocs.yml").read_text()
    assert all(f"api/{page.name}" in nav for page in pages)
