import argparse
import re

from hitl import cli


def _choices(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse keeps its subparsers only here
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _entry(name: str) -> str:
    """The docstring's text for one subcommand: its line and the indented lines after it."""
    match = re.search(rf"^  {re.escape(name)}\s+(.*?)(?=^  \S|^\S|\Z)", cli.__doc__, flags=re.M | re.S)
    assert match, f"{name} is not listed"
    return match.group(1)


def test_the_module_docstring_names_every_subcommand():
    """The docstring is the map of the command line: a subcommand added without it fails here."""
    top = _choices(cli.build_parser())
    assert set(top) == set(re.findall(r"^  ([a-z][a-z-]*)\s", cli.__doc__, flags=re.M))
    for group, parser in top.items():
        named = {w.strip(",:()") for w in _entry(group).split()}
        missing = set(_choices(parser)) - named
        assert not missing, f"hitl {group}: {sorted(missing)} not in the docstring"
