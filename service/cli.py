"""The ``articast`` command.

Each group of subcommands lives in ``service/commands/<name>.py`` and exposes
``register(subparsers)``; this module only assembles them and turns articast's own errors
into one clear line on stderr and exit status 2 (never a traceback for bad input).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from articast.core.errors import ArticastError

COMMAND_MODULES = (
    "articast.service.commands.enroll",
    "articast.service.commands.delegate",
    "articast.service.commands.model",
    "articast.service.commands.track",
    "articast.service.commands.evaluate",
    "articast.service.commands.fap",
    "articast.service.commands.transfer",
    "articast.service.commands.synth",
    "articast.service.commands.serve",
    "articast.service.commands.room",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="articast",
        description=(
            "Track the 3D speech movements of a face from one camera and stream them to "
            "avatars. Start with 'articast demo' (no camera needed)."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in COMMAND_MODULES:
        importlib.import_module(mod).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except ArticastError as exc:
        print(f"articast {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # port in use, a directory given as a file, a full disk, ...
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"articast {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"articast {args.command}: interrupted", file=sys.stderr)
        return 130


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
