"""The repository's shape: imports run one way, benchmarks stay out of the product, modules stay small,
and no committed file names the folders of the machine that wrote it.

The import graph is read from the source (``ast``), every import counted, those inside functions too
(a deferred import is still a dependency). Two graphs: the runtime one leaves out the imports under
``if TYPE_CHECKING:`` (they never run), the type-level one counts them. Neither may hold a circle (a circle
closed by a type-only import is still two modules that cannot be understood apart), and the layering
holds for both, so it is checked on the type-level graph, which contains the runtime one.

No module reaches into another module's private members (``other._name``, ``from x import _name``):
a private name used outside the module that defines it is a part of the interface nobody named.
"""

from __future__ import annotations

import ast
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("storage", "sim", "policy", "server", "web", "service", "client")
PACKAGES = (*PRODUCT, "lab", "bench", "hitl")
MAX_LINES = 500
# the packages each package may import (besides itself): the layers, bottom to top
ALLOWED = {
    "storage": set(),
    "sim": {"storage"},  # the scripted demonstrations are recorded as MCAP episodes
    "policy": {"sim", "storage"},
    "server": {"sim", "storage", "policy"},
    "web": {"sim", "storage", "policy", "server"},
    "service": {"sim", "storage", "policy", "server", "web"},
    # clients of the HTTP API: the scripted operator's expert (sim, policy), never the service itself
    "client": {"sim", "storage", "policy"},
    # the lab: simulated-operator rollouts and superseded signals, for the benchmarks and experiments only
    "lab": {"sim", "storage", "policy"},
    "bench": {"sim", "storage", "policy", "server", "web", "service", "client", "lab"},
    "hitl": {"sim", "storage", "policy", "server", "web", "service", "client", "lab", "bench"},
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


def _resolve_from(name: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` names, its relative dots resolved against ``name``."""
    base = node.module or ""
    if node.level:
        parts = name.split(".")
        anchor = parts[: len(parts) - node.level + (1 if path.name == "__init__.py" else 0)]
        base = ".".join([*anchor, base] if base else anchor)
    return base


def imports_of(name: str, path: Path, modules: set[str], *, type_checking: bool = False) -> set[str]:
    """The project modules ``name`` imports (``from pkg import sub`` counts as importing ``pkg.sub``);
    those imported under ``if TYPE_CHECKING:`` only with ``type_checking``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    skip = set() if type_checking else _type_checking_lines(tree)
    found: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _resolve_from(name, path, node)
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


def import_graph(*, type_checking: bool = False) -> dict[str, set[str]]:
    """module -> the project modules it imports: at run time, or with ``type_checking`` also for types."""
    sources = _sources()
    names = set(sources)
    return {name: imports_of(name, path, names, type_checking=type_checking) for name, path in sources.items()}


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


@pytest.mark.parametrize(
    ("type_checking", "expected"),
    [(False, {"pkg.sub", "pkg.other"}), (True, {"pkg.sub", "pkg.other", "pkg.hidden"})],
    ids=["runtime", "type-level"],
)
def test_the_import_reader_sees_deferred_and_relative_imports(tmp_path, type_checking, expected):
    mod = tmp_path / "m.py"
    mod.write_text(
        "from typing import TYPE_CHECKING\n"
        "from . import sub\n"
        "if TYPE_CHECKING:\n    import pkg.hidden\n"
        "def f():\n    import pkg.other.deep\n"
    )
    modules = {"pkg.m", "pkg", "pkg.sub", "pkg.hidden", "pkg.other"}
    assert imports_of("pkg.m", mod, modules, type_checking=type_checking) == expected


def _circles(graph: dict[str, set[str]]) -> str:
    return "\n".join(" <-> ".join(c) for c in cycles(graph))


def test_no_import_cycles_between_the_projects_modules():
    found = _circles(import_graph())
    assert not found, "import cycles:\n" + found


def test_no_import_cycles_counting_type_only_imports():
    found = _circles(import_graph(type_checking=True))
    assert not found, "import cycles closed through `if TYPE_CHECKING:` imports:\n" + found


def test_packages_import_only_the_layers_below_them():
    wrong = []
    for name, deps in import_graph(type_checking=True).items():
        package = name.split(".")[0]
        for dep in sorted(deps):
            if dep.split(".")[0] not in ALLOWED[package] | {package}:
                wrong.append(f"{name} imports {dep}")
    assert not wrong, "\n".join(wrong)


def test_no_product_module_imports_bench_or_the_lab():
    wrong = [
        f"{name} imports {dep}"
        for name, deps in import_graph(type_checking=True).items()
        if name.split(".")[0] in PRODUCT
        for dep in deps
        if dep.split(".")[0] in ("bench", "lab")
    ]
    assert not wrong, "\n".join(wrong)


# --- private members ---------------------------------------------------------------------------------

# the one module allowed to reach into libraries' private members (viser, pinned): it names them all
PRIVATE_ACCESS_ALLOWED = {"web.viser_internals"}


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _is_self(node: ast.AST) -> bool:
    return isinstance(node, ast.Name) and node.id in ("self", "cls")


def _made_here(function: ast.FunctionDef | ast.AsyncFunctionDef) -> set[str]:
    """The local variables a function binds itself (not its parameters): objects it made."""
    params = {a.arg for a in ast.walk(function.args) if isinstance(a, ast.arg)}
    bound = {n.id for n in ast.walk(function) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
    return bound - params


def private_names_defined(tree: ast.AST) -> set[str]:
    """The private names a module defines: its functions, classes and methods, the names it assigns at
    module or class level, the attributes it assigns on ``self``/``cls``, and those it sets on an object
    a function of its own made (a marker on a library's object)."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            made = _made_here(node)
            for store in ast.walk(node):
                if (
                    isinstance(store, ast.Attribute)
                    and isinstance(store.ctx, ast.Store)
                    and isinstance(store.value, ast.Name)
                    and store.value.id in made
                ):
                    names.add(store.attr)
        if isinstance(node, ast.Module | ast.ClassDef):
            for stmt in node.body:
                targets = []
                if isinstance(stmt, ast.Assign):
                    targets = stmt.targets
                elif isinstance(stmt, ast.AnnAssign | ast.AugAssign):
                    targets = [stmt.target]
                for target in targets:
                    names.update(n.id for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) and _is_self(node.value):
            names.add(node.attr)
    return {n for n in names if _is_private(n)}


def private_uses(name: str, path: Path, tree: ast.AST, foreign: set[str], modules: set[str]) -> list[str]:
    """Where module ``name`` touches a private member defined in another project module: ``x._name``
    (``x`` not ``self``/``cls``) with ``_name`` in ``foreign``, and ``from <project module> import _name``.
    Each as ``module: expr (line N)``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in foreign and not _is_self(node.value):
            found.append(f"{name}: {ast.unparse(node)} (line {node.lineno})")
        elif isinstance(node, ast.ImportFrom):
            base = _resolve_from(name, path, node)
            while base and base not in modules:
                base = base.rpartition(".")[0]
            if base and base != name:
                for alias in node.names:
                    if _is_private(alias.name):
                        found.append(f"{name}: from {base} import {alias.name} (line {node.lineno})")
    return sorted(set(found), key=lambda line: (line.split(":")[0], int(line.rpartition("line ")[2][:-1])))


def private_access(sources: dict[str, Path]) -> list[str]:
    """Every module's uses of private names that some other project module defines and it does not."""
    trees = {name: ast.parse(path.read_text(), filename=str(path)) for name, path in sources.items()}
    defined = {name: private_names_defined(tree) for name, tree in trees.items()}
    out = []
    for name, tree in trees.items():
        if name in PRIVATE_ACCESS_ALLOWED:
            continue
        foreign = set().union(*(d for other, d in defined.items() if other != name)) - defined[name]
        out.extend(private_uses(name, sources[name], tree, foreign, set(sources)))
    return out


def test_the_private_access_finder_flags_another_modules_privates(tmp_path):
    (tmp_path / "pkg").mkdir()
    owner = tmp_path / "pkg" / "owner.py"
    owner.write_text(
        "_LIMIT = 3\n"
        "def _helper(): ...\n"
        "class Fleet:\n"
        "    _count = 0\n"
        "    def __init__(self):\n        self._robots = {}\n"
        "    def _fault(self, robot): ...\n"
        "    def merge(self, other: 'Fleet'):\n        self._robots.update(other._robots)\n"  # same module
    )
    user = tmp_path / "pkg" / "user.py"
    user.write_text(
        "from pkg.owner import _LIMIT\n"
        "from .owner import Fleet, _helper\n"
        "import numpy as np\n"
        "class Loop:\n"
        "    def __init__(self):\n        self._fleet = Fleet()\n"
        "    def step(self, fleet):\n"
        "        fleet._fault(1)\n"  # a private method defined elsewhere
        "        n = len(self._fleet._robots)\n"  # private state defined elsewhere
        "        self._fleet = None\n"  # its own
        "        np.random._bit_generator\n"  # a library's: no project module defines it
        "        fleet._count = 2\n"  # a write into another module's object
        "        return fleet.__class__\n"  # dunder
    )
    assert private_access({"pkg.owner": owner, "pkg.user": user}) == [
        "pkg.user: from pkg.owner import _LIMIT (line 1)",
        "pkg.user: from pkg.owner import _helper (line 2)",
        "pkg.user: fleet._fault (line 8)",
        "pkg.user: self._fleet._robots (line 9)",
        "pkg.user: fleet._count (line 12)",
    ]
    marker = tmp_path / "pkg" / "marker.py"
    marker.write_text("import logging\ndef quiet():\n    f = logging.Filter()\n    f._count = 1\n    return f._count\n")
    assert private_access({"pkg.owner": owner, "pkg.marker": marker}) == []  # a marker on its own object


def test_no_module_touches_another_modules_private_members():
    touched = private_access(_sources())
    assert not touched, (
        "private members used outside the module that defines them (make them public, or move the code"
        " to their owner):\n" + "\n".join(touched)
    )


# A robot's mode is ``policy.hitl_state.Mode``: a mode written as a string literal in a comparison,
# an assignment to a mode, a ``mode=`` argument or a ``Literal[...]`` is a second copy of it.
MODE_VALUES = frozenset({"autonomous", "waiting", "teleop", "paused", "done", "faulted"})
MODE_SCOPE = ("server", "web")
MODE_HOME = "policy.hitl_state"


def _mode_literals(node: ast.AST) -> list[ast.Constant]:
    """String constants naming a mode in ``node`` (itself, or the items of a tuple, list or set)."""
    items = node.elts if isinstance(node, ast.Tuple | ast.List | ast.Set) else [node]
    return [n for n in items if isinstance(n, ast.Constant) and n.value in MODE_VALUES]


def _names_a_mode(target: ast.AST) -> bool:
    name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
    return "mode" in name.lower()


def mode_string_literals(tree: ast.AST) -> list[ast.Constant]:
    """Mode names written as strings where a mode is compared, assigned, passed or typed."""
    found: list[ast.Constant] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            for side in (node.left, *node.comparators):
                found += _mode_literals(side)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            flat = [e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])]
            if node.value is not None and any(_names_a_mode(t) for t in flat):
                for value in node.value.elts if isinstance(node.value, ast.Tuple) else [node.value]:
                    found += _mode_literals(value)
                    if isinstance(value, ast.IfExp):
                        found += _mode_literals(value.body) + _mode_literals(value.orelse)
        elif isinstance(node, ast.keyword) and node.arg is not None and "mode" in node.arg:
            found += _mode_literals(node.value)
        elif isinstance(node, ast.Subscript) and ast.unparse(node.value).endswith("Literal"):
            found += _mode_literals(node.slice)
    return found


def test_the_mode_literal_finder_sees_comparisons_assignments_and_literals():
    tree = ast.parse(
        "if robot.mode == 'teleop': pass\n"
        "robot.mode, robot.fault = 'faulted', None\n"
        "x = r.mode in ('paused', 'done')\n"
        "M = Literal['autonomous', 'waiting']\n"
        "f(mode='waiting')\n"
        "stage = 'done'\n"  # not a mode
        "counts = {'waiting': 1}\n"  # nor this
    )
    assert sorted(c.value for c in mode_string_literals(tree)) == [
        "autonomous", "done", "faulted", "paused", "teleop", "waiting", "waiting"
    ]  # fmt: skip


def test_no_mode_string_literal_in_server_or_web():
    assert {m.value for m in __import__(MODE_HOME, fromlist=["Mode"]).Mode} == MODE_VALUES
    found = [
        f"{name}: {c.value!r} (line {c.lineno})"
        for name, path in _sources().items()
        if name.split(".")[0] in MODE_SCOPE and name != MODE_HOME
        for c in mode_string_literals(ast.parse(path.read_text(), filename=str(path)))
    ]
    assert not found, "a robot's mode written as a string (use policy.hitl_state.Mode):\n" + "\n".join(found)


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
