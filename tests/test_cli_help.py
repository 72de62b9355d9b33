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


def _help_all(command, capsys):
    import pytest

    from articast.service.cli import main

    with pytest.raises(SystemExit) as done:
        main([command, "--help-all"])
    assert done.value.code == 0
    return capsys.readouterr().out


def test_serving_commands_help_shows_what_a_first_run_needs(capsys):
    """Issue 39: demo --help was 186 lines and 51 options for a command that needs none.
    --help lists the common options (demo in <= 40 lines) and says where the rest are;
    --help-all lists every option, each still there and working."""
    from articast.service.commands.serve import SHOWN

    for command in ("demo", "serve", "replay", "replay-record"):
        brief, full = _help(command), _help_all(command, capsys)
        assert "--help-all" in brief and "--max-queue" not in brief, command
        assert "\nserver limits:" not in brief and "--hub" not in brief, command
        for dest in SHOWN[command]:
            option = dest.replace("_", "-")
            assert option in brief or dest in ("video", "recording"), (command, option)
        everything = set(re.findall(r"--[a-z][a-z-]+", full))
        listed = {o for a in dict(walk(build_parser()))[("articast", command)]._actions
                  for o in a.option_strings if o.startswith("--")}
        assert listed <= everything, (command, listed - everything)
        assert len(brief.splitlines()) < len(full.splitlines()) / 2, command
    assert len(_help("demo").splitlines()) <= 40, _help("demo")
    # a hidden option still works: parsed as before
    args = build_parser().parse_args(["demo", "--max-queue", "8", "--worker-start-s", "30"])
    assert (args.max_queue, args.worker_start_s) == (8, 30.0)


def test_serving_commands_put_the_common_options_first_and_the_limits_last(capsys):
    """demo/replay/replay-record --help-all ran through ~190 lines of server limits before
    what matters: the common options come first, the limits in one group at the end."""
    for command in ("demo", "replay", "replay-record", "serve"):
        text = _help_all(command, capsys)
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
