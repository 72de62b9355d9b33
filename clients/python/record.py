"""``articast-record URL SESSION -o out.jsonl [--frames N]``

Record a session's frames as JSON lines (a header from ``hello``, then one line per frame,
each flushed: a crash loses at most the frame in flight). The file replays with
``articast replay-record``. Reconnects by itself if the server goes away.

A server that listens with a token (``ARTICAST_TOKEN`` or ``--token-file`` on the server)
refuses clients without it: give it in the URL, ``ws://HOST:PORT/ws?token=TOKEN``.
(``python -m articast.client.record`` is the same command.)
"""

from __future__ import annotations

import argparse
import json
import sys

from articast.client.client import (
    ClientClosed,
    ClientError,
    frame_record,
    header_record,
    subscribe_sync,
)
from articast.client.print import SESSION_HELP, URL_HELP


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="articast-record", description=__doc__.replace("``", "'"),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("url", help=URL_HELP)
    ap.add_argument("session", help=SESSION_HELP)
    ap.add_argument("-o", "--output", required=True, help="JSONL file to write")
    ap.add_argument("--frames", type=int, default=0, help="stop after N frames (0: until end)")
    ap.add_argument("--token", default=None, help="the server's token (default: "
                    "ARTICAST_TOKEN; prefer the variable: arguments show in the process list)")
    args = ap.parse_args(argv)
    n = 0
    header_written = False
    try:
        with open(args.output, "w", encoding="utf-8") as out:
            with subscribe_sync(args.url, args.session, ("articulatory", "pose"),
                                token=args.token) as sub:
                for frame in sub:
                    if not header_written and sub.hello is not None:
                        out.write(json.dumps(header_record(sub.hello)) + "\n")
                        header_written = True
                    out.write(json.dumps(frame_record(frame)) + "\n")
                    out.flush()
                    n += 1
                    if args.frames and n >= args.frames:
                        break
    except (ClientError, ClientClosed) as exc:
        print(f"record: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    print(f"{n} frames -> {args.output}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
