"""``articast-print URL SESSION`` — one live line per frame: the seven articulatory
parameters, quality and the measured latency (server send -> received, same host clock or
NTP-synchronised hosts). Ctrl-C stops.

A server that listens with a token (``ARTICAST_TOKEN`` or ``--token-file`` on the server)
refuses clients without it: give it in the URL, ``ws://HOST:PORT/ws?token=TOKEN``.
(``python -m articast.client.print`` is the same command.)"""

from __future__ import annotations

import argparse
import sys
import time

from articast.client.client import ClientClosed, ClientError, subscribe_sync

URL_HELP = ("the server's WebSocket, as 'articast serve' prints it: ws://HOST:PORT/ws "
            "(add ?token=TOKEN for a server with a token)")
SESSION_HELP = ("the session (face) to follow: a name given to 'serve --source NAME=...', "
                "'demo' for 'articast demo'; GET /api/sessions lists them")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="articast-print", description=__doc__.replace("``", "'"),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("url", help=URL_HELP)
    ap.add_argument("session", help=SESSION_HELP)
    ap.add_argument("--rate", type=float, default=None, help="max frames per second")
    ap.add_argument("--frames", type=int, default=0, help="stop after N frames")
    ap.add_argument("--token", default=None, help="the server's token (default: "
                    "ARTICAST_TOKEN; prefer the variable: arguments show in the process list)")
    args = ap.parse_args(argv)
    n = 0
    try:
        with subscribe_sync(args.url, args.session, ("articulatory", "pose"),
                            rate=args.rate, token=args.token) as sub:
            for f in sub:
                a = f.values.articulatory or {}
                lat = (time.time() - f.t_sent) * 1000
                params = " ".join(f"{k}={v:+.2f}" for k, v in a.items())
                flag = "ok" if f.quality.ok else f"NOT OK ({f.quality.reason})"
                print(f"#{f.seq:6d} t={f.t:8.3f}s {params} {flag} {lat:5.1f} ms", flush=True)
                n += 1
                if args.frames and n >= args.frames:
                    break
    except (ClientError, ClientClosed) as exc:
        print(f"print: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
