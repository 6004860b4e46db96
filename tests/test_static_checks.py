"""The checks that keep the layout honest, run by the same `python -m pytest` as every test.

Each runs the real tool over the real tree (configured in pyproject.toml) and fails with its output.
"""
from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import background
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "carto_cli"

# The kernel tests, run once more with numba off so that coverage (and Python's own integer and dtype
# rules) see inside the kernels; tests/reference holds the oracles they compare against.
# Two shards of about the same length (~65 s each alone under coverage; randomized comparisons take fewer draws
# here, tests/support.py), started with the session and run beside the other tests (tests/background.py).
KERNEL_TESTS = [["tests/matching", "tests/mapping/test_optimization.py", "tests/io/sources/test_decimals.py"],
                ["tests/sensor", "tests/grid", "tests/mapping/test_quality.py", "tests/gmapping/test_maps.py",
                 "tests/gmapping/test_matcher.py", "tests/gmapping/test_motion.py", "tests/gmapping/test_resampling.py"]]
KERNEL_PACKAGES = ["carto_cli.sensor", "carto_cli.grid", "carto_cli.matching", "carto_cli.mapping.optimization",
                   "carto_cli.mapping.see_through", "carto_cli.gmapping.maps", "carto_cli.gmapping.matcher",
                   "carto_cli.gmapping.motion", "carto_cli.gmapping.resampling", "carto_cli.io.sources.decimals"]


def _run(*cmd: str, env: dict | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def _ok(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout[-6000:]}\n{proc.stderr[-3000:]}"


def test_ruff_finds_nothing():
    _ok(_run(sys.executable, "-m", "ruff", "check", "carto_cli", "tests", "bench"))


background.register("mypy", lambda: background.Check(lambda _: [[sys.executable, "-m", "mypy", "--no-error-summary"]],
                                                     ROOT))


@pytest.mark.background("mypy")
def test_mypy_finds_nothing():
    ((code, output),) = background.take("mypy").results(timeout=900)
    assert code == 0, f"exit {code}\n{output[-6000:]}"


def test_import_contracts_hold():
    lint = Path(sys.executable).with_name("lint-imports")
    _ok(_run(str(lint) if lint.exists() else "lint-imports", "--no-cache"))


def _kernel_shards() -> background.Check:
    """The shards at once, their coverage data in the check's own directory."""
    return background.Check(lambda scratch: [
        [sys.executable, "-m", "coverage", "run", "--parallel-mode", f"--data-file={scratch / '.coverage'}",
         "--source=" + ",".join(KERNEL_PACKAGES), "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
         "-m", "not slow_without_jit", *tests] for tests in KERNEL_TESTS], ROOT, env={"NUMBA_DISABLE_JIT": "1"})


background.register("kernels without numba", _kernel_shards)


@pytest.mark.background("kernels without numba")
def test_kernel_tests_pass_with_numba_off():
    check = background.take("kernels without numba")
    for (code, output), tests in zip(check.results(timeout=1800), KERNEL_TESTS):
        assert code == 0, f"{' '.join(tests)}: exit {code}\n{output[-6000:]}"
    data = f"--data-file={check.scratch / '.coverage'}"
    _ok(_run(sys.executable, "-m", "coverage", "combine", data))
    report = _run(sys.executable, "-m", "coverage", "report", data)
    _ok(report)
    print(report.stdout)


def test_cli_imports_no_kernel_before_a_command_runs():
    """The lazy-import rule (docs/architecture.md): `carto --help` must not pay for numba."""
    probe = ("import sys, carto_cli.cli; "
             "print(sorted(m for m in ('numba', 'scipy', 'cv2', 'optuna') if m in sys.modules))")
    proc = _run(sys.executable, "-c", probe)
    _ok(proc)
    assert proc.stdout.strip() == "[]"


def test_mapping_and_relocalizing_load_no_scipy_sparse():
    """Importing scipy.sparse was a quarter of the mapping command's imports (docs/scaling.md, Start-up); the
    optimizer orders and splits its graph with its own kernels. (numba imports scipy.linalg on its own.)"""
    probe = ("import sys, carto_cli.commands.map, carto_cli.commands.relocalize, carto_cli.pipeline; "
             "print(sorted(m for m in sys.modules if m.startswith(('scipy.sparse', 'scipy.linalg'))))")
    proc = _run(sys.executable, "-c", probe)
    _ok(proc)
    assert proc.stdout.strip() == "[]"


def _python_files(*dirs: str):
    for d in dirs:
        yield from sorted((ROOT / d).rglob("*.py"))
    yield ROOT / "bench" / "run"


def _is_module(dotted: str) -> bool:
    path = ROOT / dotted.replace(".", "/")
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_imported_across_modules():
    """Neither `from carto_cli.m import _x` nor `m._x` on an imported carto_cli module."""
    offenders = []
    for path in _python_files("carto_cli", "bench", "tests"):
        tree = ast.parse(path.read_text(), str(path))
        modules = set()  # local names bound to carto_cli modules
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("carto_cli"):
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}"
                              for a in node.names if _private(a.name)]
                modules |= {a.asname or a.name for a in node.names if _is_module(f"{node.module}.{a.name}")}
            elif isinstance(node, ast.Import):
                modules |= {a.asname for a in node.names if a.name.startswith("carto_cli") and a.asname}
        offenders += [f"{path.relative_to(ROOT)}:{node.lineno} {node.value.id}.{node.attr}"
                      for node in ast.walk(tree)
                      if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                      and node.value.id in modules and _private(node.attr)]
    assert not offenders, "private names used across modules:\n" + "\n".join(offenders)


WRAP = re.compile(r"%\s*\(?\s*2(\.0)?\s*\*\s*(math|np)\.pi|atan2\(\s*(math|np)\.sin|arctan2\(\s*np\.sin|remainder\(")


def test_angle_wrapping_has_one_home():
    homes = {PACKAGE / "core" / "transform.py"}
    found = [f"{p.relative_to(ROOT)}:{i}" for p in _python_files("carto_cli", "bench")
             for i, line in enumerate(p.read_text().splitlines(), 1)
             if WRAP.search(line) and p not in homes and not line.lstrip().startswith("#")]
    assert not found, "angle wrapped outside carto_cli/core/transform.py:\n" + "\n".join(found)


@pytest.mark.parametrize("package", sorted(p.parent.name for p in PACKAGE.glob("*/__init__.py")))
def test_every_package_says_its_job(package):
    doc = ast.get_docstring(ast.parse((PACKAGE / package / "__init__.py").read_text()))
    assert doc, f"carto_cli/{package}/__init__.py has no docstring"


# Import cycles between modules still to be broken, each named in full: none now (issue 44 removed the last four). A
# cycle not listed here fails, and so does a listed one that is gone (remove it from the list).
KNOWN_CYCLES: list[set[str]] = []


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the carto_cli modules it imports, at the top or inside a function (a lazy import is still a
    dependency); a package's ``__init__`` (re-exports) is neither a source nor a target."""
    files = {_module_name(p): p for p in _python_files("carto_cli")}
    modules = {m for m, p in files.items() if p.name != "__init__.py"}

    def resolve(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name if name in modules else None

    graph: dict[str, set[str]] = {m: set() for m in modules}
    for m in modules:
        package = m.rpartition(".")[0].split(".")
        for node in ast.walk(ast.parse(files[m].read_text(), str(files[m]))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(package[:len(package) - node.level + 1] + [node.module or ""]).strip(".") \
                    if node.level else node.module or ""
                names = [f"{base}.{a.name}" for a in node.names] + [base]
            graph[m] |= {t for t in map(resolve, names) if t and t != m}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.add(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(component)
    return found


def test_no_import_cycle_between_modules():
    cycles = _cycles(_import_graph())
    new = [sorted(c) for c in cycles if c not in KNOWN_CYCLES]
    gone = [sorted(c) for c in KNOWN_CYCLES if c not in cycles]
    assert not new, "modules that import each other (directly or around a loop):\n" + "\n".join(map(str, new))
    assert not gone, "cycles listed in KNOWN_CYCLES that are gone: remove them from the list\n" + "\n".join(map(str, gone))


def test_the_cycle_finder_finds_a_cycle_and_nothing_else():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"d"}}
    assert _cycles(graph) == [{"a", "b", "c"}]
    assert _cycles({"a": {"b"}, "b": set()}) == []


# Functions over ruff's complexity limits (mccabe 10, pylint's 12 branches and 50 statements) on the day the rules
# came in, one "path::function rule" a line: a ratchet. Listing them by function, not ignoring the rules per file,
# keeps a file that has one from taking a second (issue 44).
COMPLEXITY_RULES = "C901,PLR0912,PLR0915"
COMPLEXITY_LIST = ROOT / "tests" / "complexity_offenders.txt"


def _def_names(path: Path) -> dict[int, str]:
    """Line of each def -> its qualified name (Class.method, outer.inner)."""
    names: dict[int, str] = {}

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                if not isinstance(child, ast.ClassDef):
                    names[child.lineno] = name
                walk(child, name + ".")
            else:
                walk(child, prefix)

    walk(ast.parse(path.read_text(), str(path)), "")
    return names


def complexity_offenders() -> set[str]:
    proc = _run(sys.executable, "-m", "ruff", "check", "--select", COMPLEXITY_RULES, "--output-format", "json",
                "--exit-zero", "carto_cli", "bench")
    _ok(proc)
    found = set()
    names: dict[Path, dict[int, str]] = {}
    for d in json.loads(proc.stdout):
        path = Path(d["filename"])
        if path not in names:
            names[path] = _def_names(path)
        found.add(f"{path.relative_to(ROOT)}::{names[path][d['location']['row']]} {d['code']}")
    return found


def test_no_function_grows_past_the_complexity_limits():
    listed = {line.strip() for line in COMPLEXITY_LIST.read_text().splitlines() if line.strip()
              and not line.startswith("#")}
    found = complexity_offenders()
    new, fixed = sorted(found - listed), sorted(listed - found)
    assert not new, f"over ruff's complexity limits ({COMPLEXITY_RULES}); split them:\n" + "\n".join(new)
    assert not fixed, f"no longer over the limits: remove from {COMPLEXITY_LIST.name}\n" + "\n".join(fixed)
