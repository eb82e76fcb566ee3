"""The repository's shape: imports run one way, benchmarks stay out of the product, modules stay small,
and no committed file names the folders of the machine that wrote it.

The import graph is read from the source (``ast``), every import counted, those inside functions too
(a deferred import is still a dependency); only imports under ``if TYPE_CHECKING:`` are left out, since
they never run.
"""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("storage", "sim", "policy", "server", "web", "service")
PACKAGES = (*PRODUCT, "bench", "hitl")
MAX_LINES = 500
# the packages each package may import (besides itself): the layers, bottom to top
ALLOWED = {
    "storage": set(),
    "sim": {"storage"},  # the scripted demonstrations are recorded as MCAP episodes
    "policy": {"sim", "storage"},
    "server": {"sim", "storage", "policy"},
    "web": {"sim", "storage", "policy", "server"},
    "service": {"sim", "storage", "policy", "server", "web"},
    "bench": {"sim", "storage", "policy", "server", "web", "service"},
    "hitl": {"sim", "storage", "policy", "server", "web", "service", "bench"},
}


def _tracked(*patterns: str) -> list[Path]:
    out = subprocess.run(["git", "ls-files", *patterns], cwd=ROOT, capture_output=True, text=True, check=True)
    return [ROOT / line for line in out.stdout.splitlines() if (ROOT / line).is_file()]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _sources() -> dict[str, Path]:
    """Every module of the project's packages, tracked or new (a new file must obey the rules too)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if "migrations" not in path.parts:
                found[_module_name(path)] = path
    return found


def _type_checking_lines(tree: ast.AST) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


def imports_of(name: str, path: Path, modules: set[str]) -> set[str]:
    """The project modules ``name`` imports (``from pkg import sub`` counts as importing ``pkg.sub``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    skip = _type_checking_lines(tree)
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for target in targets:
            # the module itself, or the closest enclosing project module (``import a.b.c`` of a package)
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def import_graph() -> dict[str, set[str]]:
    sources = _sources()
    names = set(sources)
    return {name: imports_of(name, path, names) for name, path in sources.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_reader_sees_deferred_and_relative_imports(tmp_path):
    mod = tmp_path / "m.py"
    mod.write_text(
        "from typing import TYPE_CHECKING\n"
        "from pkg import sub\n"
        "if TYPE_CHECKING:\n    import pkg.hidden\n"
        "def f():\n    import pkg.other.deep\n"
    )
    modules = {"pkg.m", "pkg", "pkg.sub", "pkg.hidden", "pkg.other"}
    assert imports_of("pkg.m", mod, modules) == {"pkg.sub", "pkg.other"}


def test_no_import_cycles_between_the_projects_modules():
    found = cycles(import_graph())
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_packages_import_only_the_layers_below_them():
    wrong = []
    for name, deps in import_graph().items():
        package = name.split(".")[0]
        for dep in sorted(deps):
            if dep.split(".")[0] not in ALLOWED[package] | {package}:
                wrong.append(f"{name} imports {dep}")
    assert not wrong, "\n".join(wrong)


def test_no_product_module_imports_bench():
    wrong = [
        f"{name} imports {dep}"
        for name, deps in import_graph().items()
        if name.split(".")[0] in PRODUCT
        for dep in deps
        if dep.split(".")[0] == "bench"
    ]
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("package", PRODUCT)
def test_product_modules_stay_under_the_line_limit(package):
    long = {
        str(p.relative_to(ROOT)): n
        for p in (ROOT / package).rglob("*.py")
        if "migrations" not in p.parts and (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"modules over {MAX_LINES} lines (split them along what changes together): {long}"


# a quoted path under a machine's own folders, as a config or result file would record it
MACHINE_PATH = re.compile(r"""["'](/work|/root|/home|/Users|/tmp|/var/folders)/""")
DATA_FILES = ("*.json", "*.toml", "*.md", "*.yaml", "*.yml", "*.txt", "*.csv")


def test_no_committed_file_names_a_machine_path():
    checkout = str(ROOT)
    named = []
    for path in _tracked():
        try:
            text = path.read_text()
        except (UnicodeDecodeError, OSError):
            continue  # binary files (weights, figures)
        rel = str(path.relative_to(ROOT))
        if checkout in text:
            named.append(f"{rel}: names this checkout ({checkout})")
        elif any(path.match(p) for p in DATA_FILES) and MACHINE_PATH.search(text):
            named.append(f"{rel}: {MACHINE_PATH.search(text).group(0)}...")
    assert not named, "files naming a machine's absolute path (record paths relative to a data root):\n" + "\n".join(
        named
    )
