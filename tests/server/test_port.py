"""The REST API and the console reach the fleet runtime only through ``server.port.FleetPort``."""

import ast
import inspect
import textwrap
from pathlib import Path

from server.fleet.fleet import Fleet
from server.port import MEMBERS, FleetPort

ROOT = Path(__file__).resolve().parents[2]


def _fleet_attributes(tree: ast.AST) -> set[tuple[int, str]]:
    """(line, name) of every ``fleet.name``, ``self.fleet.name`` and ``self._fleet.name``."""
    found = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        owner = node.value
        name = owner.id if isinstance(owner, ast.Name) else owner.attr if isinstance(owner, ast.Attribute) else None
        if name in ("fleet", "_fleet"):
            found.add((node.lineno, node.attr))
    return found


def test_the_api_and_the_console_use_only_the_port():
    used, past = set(), []
    for path in sorted([*(ROOT / "server" / "api").glob("*.py"), *(ROOT / "web").glob("*.py")]):
        for line, name in _fleet_attributes(ast.parse(path.read_text())):
            used.add(name)
            if name not in MEMBERS:
                past.append(f"{path.relative_to(ROOT)}:{line}: fleet.{name}")
    assert not past, "reaches past server.port.FleetPort:\n" + "\n".join(past)
    assert {"claim", "release", "command", "views"} <= used  # the check sees the calls it is about


def test_the_fleet_implements_the_port_with_its_signatures():
    for name in MEMBERS:
        ours, theirs = getattr(FleetPort, name), getattr(Fleet, name, None)
        if isinstance(ours, property):  # a property, or an attribute the fleet sets
            assert isinstance(theirs, property) or f"self.{name} = " in inspect.getsource(Fleet), name
            continue
        assert list(inspect.signature(ours).parameters) == list(inspect.signature(theirs).parameters), name


def test_each_route_that_calls_a_port_member_needs_the_role_the_port_names():
    """One role rule: the REST route and the console (``web.actions``) both take it from ``server.port.NEEDS``."""
    import importlib

    from fastapi.routing import APIRoute

    from server.port import NEEDS

    checked = set()
    for path in sorted((ROOT / "server" / "api").glob("*.py")):
        router = getattr(importlib.import_module(f"server.api.{path.stem}"), "router", None)
        for route in router.routes if router is not None else ():
            if not isinstance(route, APIRoute):
                continue
            source = textwrap.dedent(inspect.getsource(route.endpoint))
            calls = {name for _, name in _fleet_attributes(ast.parse(source))} & set(NEEDS)
            roles = {getattr(d.call, "role", None) for d in route.dependant.dependencies} - {None}
            for member in calls:
                assert roles == {NEEDS[member]}, (route.path, member, roles)
                checked.add(member)
    assert {"claim", "release", "command", "heartbeat", "pause", "reset"} <= checked
