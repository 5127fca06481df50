"""The package's import graph, read with ``ast`` from every module in the tree.

No import cycles; ROS only under vbrl_ros/ros/; no private name taken from
another module; the live node loads no training code. Every import counts,
including those inside functions and ``TYPE_CHECKING`` blocks.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class Import:
    module: str  # the importing module
    target: str  # the imported module (absolute), or the package a name is taken from
    names: tuple[str, ...]  # the names taken with `from target import ...` (empty for `import`)
    line: int


def _package_of(module: str, path: Path) -> str:
    return module if path.name == "__init__.py" else module.rpartition(".")[0]


def imports_of(module: str, path: Path) -> list[Import]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [Import(module, alias.name, (), node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package, `level - 1` packages up
                package = _package_of(module, path).split(".")
                package = package[: len(package) - node.level + 1]
                base = ".".join(package + ([base] if base else []))
            out.append(Import(module, base, tuple(alias.name for alias in node.names), node.lineno))
    return out


@pytest.fixture(scope="module")
def imports(package_modules: dict[str, Path]) -> list[Import]:
    return [imp for module, path in package_modules.items() for imp in imports_of(module, path)]


@pytest.fixture(scope="module")
def graph(package_modules: dict[str, Path], imports: list[Import]) -> dict[str, set[str]]:
    """module -> the package modules it imports (a `from package import submodule` names the submodule)."""
    edges: dict[str, set[str]] = {module: set() for module in package_modules}
    for imp in imports:
        targets = [f"{imp.target}.{name}" for name in imp.names
                   if f"{imp.target}.{name}" in package_modules]
        if imp.target in package_modules and (len(targets) < len(imp.names) or not imp.names):
            targets.append(imp.target)  # names defined in (or re-exported by) the target itself
        edges[imp.module].update(targets)
    return edges


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module, or a module importing itself."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                found.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_tree_is_read(package_modules: dict[str, Path]) -> None:
    for module in ("vbrl_ros.ros.node", "vbrl_ros.index.keyframe_index", "vbrl_ros.tools.cli"):
        assert module in package_modules
    assert len(package_modules) > 80


def test_there_are_no_import_cycles(graph: dict[str, set[str]]) -> None:
    assert cycles(graph) == []


def test_the_cycle_finder_finds_cycles() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"a"}}) == [["a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_only_the_ros_package_imports_ros(imports: list[Import], ros_packages: tuple[str, ...]) -> None:
    outside = [f"{imp.module}:{imp.line} imports {imp.target}" for imp in imports
               if imp.target.split(".")[0] in ros_packages
               and not imp.module.startswith("vbrl_ros.ros.") and imp.module != "vbrl_ros.ros"]
    assert outside == []
    inside = {imp.module for imp in imports if imp.target.split(".")[0] in ros_packages}
    assert "vbrl_ros.ros.node" in inside  # the check sees what it looks for


def test_no_private_name_is_taken_from_another_module(package_modules: dict[str, Path],
                                                      imports: list[Import]) -> None:
    taken = [f"{imp.module}:{imp.line} takes {imp.target}.{name}" for imp in imports
             if imp.target.startswith("vbrl_ros") and imp.target != imp.module
             for name in imp.names if name.startswith("_") and not name.startswith("__")]
    assert taken == []
    # nor through a module object: `from vbrl_ros.index import keys as kk` ... kk._nibble_codes
    used = []
    for module, path in package_modules.items():
        tree = ast.parse(path.read_text())
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("vbrl_ros"):
                aliases.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names
                                if f"{node.module}.{a.name}" in package_modules})
            elif isinstance(node, ast.Import):
                aliases.update({a.asname: a.name for a in node.names
                                if a.asname and a.name in package_modules})
        used += [f"{module}:{node.lineno} uses {aliases[node.value.id]}.{node.attr}"
                 for node in ast.walk(tree)
                 if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                 and node.value.id in aliases and node.attr.startswith("_")
                 and not node.attr.startswith("__")]
    assert used == []


def _closure(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module loaded by importing ``start``: its imports, theirs, and each one's packages."""
    seen, todo = set(), [start]
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        parents = [module.rsplit(".", k)[0] for k in range(1, module.count(".") + 1)]
        todo += [m for m in (*graph.get(module, ()), *parents) if m in graph]
    return seen


def test_the_node_loads_no_training_code(graph: dict[str, set[str]]) -> None:
    loaded = _closure(graph, "vbrl_ros.ros.node")
    assert {"vbrl_ros.model.builtin", "vbrl_ros.detection.detector"} <= loaded
    assert sorted(m for m in loaded if m.startswith("vbrl_ros.training")) == []


def test_importing_the_node_loads_no_training_code() -> None:
    pytest.importorskip("rclpy")
    code = ("import sys, vbrl_ros.ros.node, vbrl_ros.ros.detector_node\n"
            "print(','.join(sorted(m for m in sys.modules if m.startswith('vbrl_ros.training'))))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""
