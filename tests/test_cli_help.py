"""Help that teaches: every command has a description, every option and positional a help
text; the README's command table names every command."""

import argparse
import re
from pathlib import Path

from articast.service.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def walk(parser, path=("articast",)):
    """(command path, parser) for the parser and every sub-command, depth first."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from walk(sub, (*path, name))


def test_every_command_option_and_positional_has_help():
    missing = []
    for path, parser in walk(build_parser()):
        if len(path) > 1 and not (parser.description or "").strip():
            missing.append(f"{' '.join(path)}: no description")
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
                continue
            if action.help in (None, "") or action.help == argparse.SUPPRESS:
                name = "/".join(action.option_strings) or action.dest
                missing.append(f"{' '.join(path)}: {name}")
    assert not missing, "no help:\n" + "\n".join(missing)


def test_readme_lists_every_command():
    readme = (ROOT / "README.md").read_text()
    table = {m.group(1) for m in re.finditer(r"^\| `articast ([a-z-]+(?: [a-z][a-z-]*)?)", readme,
                                             re.M)}
    commands = set()
    for path, _ in walk(build_parser()):
        if len(path) == 2:
            commands.add(path[1])
        elif len(path) == 3:
            commands.add(f"{path[1]} {path[2]}")
    listed = {c for c in commands
              if c in table or c.split()[0] in table or any(t.startswith(c + " ") for t in table)}
    assert listed == commands, f"not in the README's command table: {commands - listed}"
