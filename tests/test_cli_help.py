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


def _help(*command):
    parser = dict(walk(build_parser()))[("articast", *command)]
    return parser.format_help()


def test_serving_commands_put_the_common_options_first_and_the_limits_last():
    """demo/replay/replay-record --help ran through ~190 lines of server limits before what
    matters: the common options come first, the limits in one group at the end."""
    for command in ("demo", "replay", "replay-record", "serve"):
        text = _help(command)
        usage = text.split("\n\n")[0]
        assert len(usage.splitlines()) <= 3 and "--max-queue" not in usage, (command, usage)
        head = "\n".join(text.splitlines()[:45])
        assert "--port" in head and "--max-queue" not in head, (command, head)
        sections = re.findall(r"^(\S[^\n]*):$", text, re.M)
        assert sections[-1] == "server limits", (command, sections)
        limits = text.split("\nserver limits:\n", 1)[1]
        for option in ("--max-queue", "--max-subscribers", "--retry-max-s",
                       "--worker-stall-s", "--shutdown-timeout-s"):
            assert option in limits and option not in text.split("\nserver limits:\n")[0]


def test_replay_record_lists_no_tracking_options():
    text = _help("replay-record")
    for option in ("--speaker", "--model", "--appearance", "--camera", "--processor",
                   "--preview"):
        assert option not in text, option
    assert "--loop" in text and "--plays" in text
