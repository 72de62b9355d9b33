"""``articast serve``, ``demo``, ``replay`` and ``replay-record``: run the streaming service."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from articast.service.settings import (
    CaptureSettings,
    HubSettings,
    ServerSettings,
    SessionPolicy,
    add_arguments,
    from_args,
)

if TYPE_CHECKING:
    from articast.service.security import AccessPolicy

EPILOG = """\
Clients connect to ws://HOST:PORT/ws and send
  {"type": "subscribe", "session": "NAME", "streams": ["articulatory", "pose"]}
The protocol is served at http://HOST:PORT/api/protocol and described in docs/SERVICE.md.
Every option is also settable as an ARTICAST_<OPTION> environment variable.
"""
BRIEF_EPILOG = EPILOG + """\
--help-all shows every option: access, Redis, the server limits.
"""

SHOWN = {
    "demo": ("seed", "fps", "host", "port", "json", "vmc", "record", "preview"),
    "serve": ("source", "speaker", "readers", "model", "appearance", "camera", "processor",
              "host", "port", "json", "vmc", "record", "preview", "wait_for_subscriber",
              "token_file"),
    "replay": ("video", "speaker", "readers", "model", "appearance", "camera", "name", "pace",
               "loop", "plays", "start", "end", "host", "port", "json", "vmc", "record",
               "preview"),
    "replay-record": ("recording", "name", "pace", "loop", "plays", "host", "port", "json",
                      "vmc", "record"),
}
"""The options each serving command's --help shows (what a first run needs); --help-all
shows every one (issue 39: demo --help was 186 lines and 51 options)."""


def brief_help(p: argparse.ArgumentParser, shown: tuple[str, ...]) -> None:
    """``--help`` lists the options in ``shown`` (and itself); ``--help-all`` every one. The
    others keep their help text (and work as before): only the brief listing skips them."""
    hidden = {id(a) for a in p._actions
              if a.dest not in (*shown, "help") and a.option_strings}

    class Brief(argparse.RawDescriptionHelpFormatter):
        show_all = False

        def add_argument(self, action: argparse.Action) -> None:
            if self.show_all or id(action) not in hidden:
                super().add_argument(action)

    quiet = [g for g in p._action_groups if g.description and g._group_actions
             and all(id(a) in hidden for a in g._group_actions)]
    descriptions = {id(g): g.description for g in quiet}
    for g in quiet:  # a group with nothing shown says nothing
        g.description = None

    class HelpAll(argparse.Action):
        def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
            Brief.show_all = True
            for g in quiet:
                g.description = descriptions[id(g)]
            parser.epilog = EPILOG
            parser.print_help()
            parser.exit()

    p.add_argument("--help-all", action=HelpAll, nargs=0,
                   help="show every option (access, Redis, server limits) and exit")
    hidden.discard(id(p._actions[-1]))
    p.formatter_class = Brief
    p.epilog = BRIEF_EPILOG


def register(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "serve", help="track faces and stream them to WebSocket subscribers",
        usage="%(prog)s --source NAME=URI [--source ...] [--speaker DIR | --model M "
              "--appearance A --camera C] [--port N] [options; --help-all: every one]",
        description="Run the streaming service with one session per --source.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--source", action="append", default=[], metavar="NAME=URI",
                   help="a session: v4l2:/dev/video0?width=640&height=480&fps=60, "
                   "file:talk.mp4?pace=realtime&loop=yes (loop=no, the default, plays "
                   "once; plays=N; start=12.5&end=900f: a part, in seconds or frames), "
                   "images:DIR, synthetic:seed=3, "
                   "replay-record:rec.jsonl (repeat for several faces; none: add them with "
                   "POST /api/sessions)")
    _common(s)
    brief_help(s, SHOWN["serve"])
    s.set_defaults(func=_serve)

    d = sub.add_parser(
        "demo", help="serve the built-in synthetic speaker on loopback",
        usage="%(prog)s [--port N] [--fps FPS] [options; --help-all: every one]",
        description="Serve the synthetic speaker (no camera, no files needed) and print the "
        "URL a client connects to.", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    d.add_argument("--seed", type=int, default=1, help="sentence seed (default 1)")
    d.add_argument("--fps", type=float, default=60.0, help="frame rate (default 60)")
    _common(d)
    brief_help(d, SHOWN["demo"])
    d.set_defaults(func=_demo)

    r = sub.add_parser(
        "replay", help="serve a recorded video through the tracker",
        usage="%(prog)s VIDEO (--speaker DIR | --model M --appearance A --camera C) "
              "[--loop] [--start WHEN] [--end WHEN] [--port N] [options; --help-all: every one]",
        description="Track a video file as if it were a camera and stream it (one session, "
        "named after the file). Give --speaker DIR (from 'articast enroll'), or the "
        "speaker's --model, --appearance and --camera.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    r.add_argument("video", type=Path, help="video file to track and stream")
    _playback(r)
    from articast.service.commands.track import add_span_arguments

    add_span_arguments(r)
    _common(r)
    brief_help(r, SHOWN["replay"])
    r.set_defaults(func=_replay)

    rr = sub.add_parser(
        "replay-record", help="serve a recording made by serve --record",
        usage="%(prog)s RECORDING [--loop | --plays N] [--pace fast] [--port N] "
              "[options; --help-all: every one]",
        description="Stream a recording (serve --record, or articast-record) "
        "again, with the same hello and frames at their recorded times: no tracking, no "
        "camera.", epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    rr.add_argument("recording", type=Path, help="recording (.jsonl)")
    _playback(rr)
    _common(rr, tracking=False)
    brief_help(rr, SHOWN["replay-record"])
    rr.set_defaults(func=_replay_record)

    w = sub.add_parser(
        "track-worker", help="track faces and publish them to Redis (serves no socket)",
        description="The capture + tracking role of a deployment on Redis: one session per "
        "--source, published on the hub; 'articast gateway' processes serve the subscribers. "
        "Reconnects to Redis by itself.", formatter_class=argparse.RawDescriptionHelpFormatter)
    w.add_argument("--source", action="append", default=[], metavar="NAME=URI",
                   help="a session, as for 'serve' (repeat for several faces)")
    _hub_argument(w, required=True)
    g = _session_files(w)
    g.add_argument("--record", default=None, help="write every session's frames as JSONL "
                   "into this folder")
    add_arguments(w.add_argument_group("capture"), CaptureSettings)
    add_arguments(w.add_argument_group("sessions"), SessionPolicy)
    w.add_argument("--json", action="store_true", help="print the start-up line as JSON")
    w.set_defaults(func=_track_worker)

    gw = sub.add_parser(
        "gateway", help="serve WebSocket subscribers from Redis (tracks nothing)",
        description="The subscriber-facing role of a deployment on Redis: serves every "
        "session any 'articast track-worker' publishes. Reconnects to Redis by itself.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _hub_argument(gw, required=True)
    add_access_arguments(gw.add_argument_group("access"))
    add_arguments(gw.add_argument_group("server"), ServerSettings, skip=("record", "vmc"))
    add_arguments(gw.add_argument_group("fan-out limits"), HubSettings)
    gw.add_argument("--json", action="store_true", help="print the start-up line as JSON")
    gw.set_defaults(func=_gateway)


def _hub_argument(p: argparse.ArgumentParser | argparse._ArgumentGroup,
                  required: bool = False) -> None:
    p.add_argument("--hub", default=None, required=False, metavar="URL",
                   help="redis://HOST:PORT/DB: sessions and subscribers meet in Redis "
                   + ("(required; env ARTICAST_HUB)" if required else
                      "(default: the in-memory hub of this process; env ARTICAST_HUB)"))
    p.add_argument("--hub-prefix", default=None, metavar="PREFIX",
                   help="Redis key/channel prefix (default articast:; env ARTICAST_HUB_PREFIX)")


def hub_url(args: argparse.Namespace, required: bool = False) -> str:
    import os

    from articast.core.errors import InputError

    url = args.hub if args.hub is not None else os.environ.get("ARTICAST_HUB", "")
    if not url:
        if required:
            raise InputError("--hub redis://HOST:PORT/DB is required (or env ARTICAST_HUB)")
        return ""
    if url in ("memory", "memory:"):
        if required:
            raise InputError("this role needs a Redis hub: --hub redis://HOST:PORT/DB")
        return ""
    if not url.startswith(("redis://", "rediss://", "unix://")):
        raise InputError(f"--hub {url!r}: expected redis://HOST:PORT/DB (or rediss://, "
                         "unix://)")
    try:
        import redis  # noqa: F401
    except ImportError:
        raise InputError("--hub redis:// needs the redis package: pip install "
                         "'articast[redis]'") from None
    return url


def hub_prefix(args: argparse.Namespace) -> str:
    import os

    return args.hub_prefix or os.environ.get("ARTICAST_HUB_PREFIX", "") or "articast:"


def _playback(p: argparse.ArgumentParser) -> None:
    p.add_argument("--name", help="session name (default: the file name)")
    p.add_argument("--pace", choices=("realtime", "fast"), default="realtime",
                   help="realtime (default): frames at their media time; fast: as fast as "
                   "they are taken, none lost")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--loop", action="store_true",
                   help="play forever (default: once, then the session is 'ended')")
    g.add_argument("--plays", type=int, default=None, metavar="N", help="play N times")


def _session_files(p: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The "session" option group: what every session tracks with (serve and track-worker)."""
    g = p.add_argument_group("session")
    g.add_argument("--speaker", default="",
                   help="speaker folder from 'articast enroll' for every session (replaces "
                        "--model, --appearance, --camera)")
    g.add_argument("--model", default="", help="face model (.npz) for every session")
    g.add_argument("--appearance", default="", help="trained appearance (.npz)")
    g.add_argument("--camera", default="", help="camera calibration (.json)")
    g.add_argument("--processor", default="auto",
                   help="auto | truth | tracker | live | module:factory (default auto)")
    g.add_argument("--readers", type=int, choices=(1, 2), default=1,
                   help="with --speaker: 2 tracks each face with two landmark readers "
                        "(FaceMesh v1 and FaceLandmarker v2), streaming the mean: lips read "
                        "better on faces the enrolment never saw, at ~3x the CPU a frame "
                        "(docs/RESULTS.md, 'Two readers live'); default 1")
    return g


def session_options(args: argparse.Namespace) -> dict:
    """The sessions' options from the command line (``--readers``), the speaker folder loaded
    once to check it and them now: one clear error, not a worker restarting."""
    from articast.core.errors import InputError

    readers = getattr(args, "readers", 1)
    if not args.speaker:
        if readers != 1:
            raise InputError(f"--readers {readers} needs --speaker (a speaker folder from "
                             "'articast enroll')")
        return {}
    from articast.core.faces.speaker import Speaker
    from articast.core.faces.two_readers import readers_problem

    problem = readers_problem(Speaker.load(args.speaker), readers)  # (a wrong folder too)
    if problem:
        raise InputError(f"--readers {readers}: {problem}")
    return {} if readers == 1 else {"readers": readers}


COMMON_SERVER = ("host", "port", "record", "log_level", "scan")
"""ServerSettings shown with the command's own options; the rest go to their groups."""


def _common(p: argparse.ArgumentParser, tracking: bool = True) -> None:
    """The options every serving command shares, the ones people use first: where to listen,
    what to track with, access; the ~60 limits of a long-running server last, in one group.
    ``tracking=False`` (replay-record: the recording brings its frames) leaves out the
    options that would do nothing."""
    add_arguments(p, ServerSettings, skip=tuple(f.name for f in dataclasses.fields(
        ServerSettings) if f.name not in COMMON_SERVER))
    p.add_argument("--json", action="store_true", help="print the start-up line as JSON")
    if tracking:
        g = _session_files(p)
    else:
        g = p.add_argument_group("session")
        p.set_defaults(speaker="", model="", appearance="", camera="", processor="auto",
                       preview=False)
    g.add_argument("--wait-for-subscriber", action="store_true",
                   help="hold each source until its first subscriber arrives")
    if tracking:
        g.add_argument("--preview", action=argparse.BooleanOptionalAction, default=None,
                       help="serve a small, low-rate preview of the tracked video with the "
                       "fit drawn on it (GET /api/sessions/NAME/preview.jpg; the browser "
                       "avatar shows it). Off by default for privacy; on for the synthetic "
                       "demo")
        g.add_argument("--delegate", action=argparse.BooleanOptionalAction, default=True,
                       help="serve the speaker's own textured face (the delegate.npz 'articast "
                       "enroll' writes into the speaker folder) to subscribers with the token, "
                       "for the browser avatar (default on; --no-delegate serves none: the "
                       "avatar shows a generic face)")
    add_arguments(p.add_argument_group("VMC (VTuber apps)"), ServerSettings,
                  skip=tuple(f.name for f in dataclasses.fields(ServerSettings)
                             if not f.name.startswith("vmc")))
    a = p.add_argument_group("access")
    add_access_arguments(a)
    a.add_argument("--api-token", default=None, metavar="REMOVED",
                   help="removed: a token on the command line is visible in the process list; "
                        "set ARTICAST_TOKEN or use --token-file")
    _hub_argument(p.add_argument_group("scale-out on Redis (docs/SERVICE.md)"))
    limits = p.add_argument_group(
        "server limits", "Bounds of a long-running server; the defaults suit one machine "
        "(docs/SERVICE.md, Access control and Settings). Each is also an ARTICAST_* variable.")
    add_arguments(limits, ServerSettings, skip=tuple(
        f.name for f in dataclasses.fields(ServerSettings)
        if f.name in COMMON_SERVER or f.name.startswith("vmc")))
    add_arguments(limits, HubSettings)
    add_arguments(limits, CaptureSettings)
    add_arguments(limits, SessionPolicy)


def add_access_arguments(a: argparse._ArgumentGroup) -> None:
    a.add_argument("--token-file", default=None, metavar="FILE",
                   help="read the access token from FILE (else env ARTICAST_TOKEN); clients "
                   "send it as 'Authorization: Bearer TOKEN' or ?token=TOKEN")
    a.add_argument("--insecure-no-token", action="store_true", default=None,
                   help="allow listening on a non-loopback address without a token "
                   "(anyone reaching the port sees every face; env ARTICAST_INSECURE_NO_TOKEN)")
    a.add_argument("--allowed-origin", action="append", default=[], metavar="ORIGIN",
                   help="a browser origin allowed besides this server's own and loopback "
                   "(e.g. https://app.example; repeatable; env ARTICAST_ALLOWED_ORIGINS, "
                   "comma-separated)")
    a.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                   help="a Host name this server answers to besides its address and loopback "
                   "(repeatable; env ARTICAST_ALLOWED_HOSTS, comma-separated; * = any)")
    a.add_argument("--media-root", action="append", default=[], metavar="DIR",
                   help="sessions added over HTTP may open files under DIR (repeatable; env "
                   "ARTICAST_MEDIA_ROOT, ':'-separated; none: no files)")
    a.add_argument("--allow-device", action="append", default=[], metavar="DEV",
                   help="sessions added over HTTP may open this camera, e.g. /dev/video0 "
                   "(repeatable; env ARTICAST_ALLOW_DEVICE, comma-separated)")


def access_policy(args: argparse.Namespace, host: str) -> AccessPolicy:
    """The AccessPolicy of the command line and the environment; refuses unsafe binding."""
    import os

    from articast.core.errors import InputError
    from articast.service.security import (
        AccessPolicy,
        check_token_strength,
        is_loopback,
        load_token,
    )

    if getattr(args, "api_token", None) is not None:
        raise InputError("--api-token is gone: a token on the command line is visible to "
                         "every user in the process list; set ARTICAST_TOKEN or use "
                         "--token-file FILE")
    env = os.environ
    token = load_token(env, args.token_file or env.get("ARTICAST_TOKEN_FILE", ""))
    check_token_strength(token)
    insecure = args.insecure_no_token or env.get("ARTICAST_INSECURE_NO_TOKEN", "").lower() in (
        "1", "true", "yes", "on")
    if not token and not is_loopback(host) and not insecure:
        raise InputError(f"refusing to listen on {host} without a token: set ARTICAST_TOKEN "
                         "or --token-file FILE (or --insecure-no-token on a trusted network)")

    def listed(values: list[str], key: str, sep: str) -> tuple[str, ...]:
        extra = [v.strip() for v in env.get(key, "").split(sep) if v.strip()]
        return tuple(dict.fromkeys([*values, *extra]))

    roots = listed(args.media_root, "ARTICAST_MEDIA_ROOT", os.pathsep)
    for r in roots:
        if not os.path.isdir(r):
            raise InputError(f"--media-root {r}: not a folder")
    return AccessPolicy(
        token=token, bind_host=host,
        allowed_hosts=listed(args.allowed_host, "ARTICAST_ALLOWED_HOSTS", ","),
        allowed_origins=listed(args.allowed_origin, "ARTICAST_ALLOWED_ORIGINS", ","),
        media_roots=tuple(os.path.realpath(r) for r in roots),
        allowed_devices=listed(args.allow_device, "ARTICAST_ALLOW_DEVICE", ","))


def _run(args: argparse.Namespace, sources: list[tuple[str, str]]) -> int:
    if sources:  # the workers' imports run beside the server's own from here on
        from articast.service.worker import start_worker_server

        start_worker_server()
    from articast.core.errors import InputError
    from articast.service.app import ServiceConfig
    from articast.service.server import serve
    from articast.service.sources import probe
    from articast.service.worker import SessionSpec

    server = from_args(ServerSettings, args)
    access = access_policy(args, server.host)  # before probing: refuse fast and cheaply
    names = [n for n, _ in sources]
    if len(set(names)) != len(names):
        raise InputError(f"session names must differ: {names}")
    from articast.service.processors import check_processor
    from articast.service.sources import parse_uri

    for _, uri in sources:
        probe(uri)  # a corrupt file or unknown kind: one clear error now, not a server later
        check_processor(args.processor, parse_uri(uri).kind,
                        bool(args.appearance or args.speaker))
    preview = bool(args.preview) if args.preview is not None else args.func is _demo
    options = session_options(args)  # (a wrong speaker folder: one clear error now)
    specs = tuple(SessionSpec(n, uri, args.model, args.appearance, args.camera, args.processor,
                              args.wait_for_subscriber, options=options, speaker=args.speaker,
                              preview=preview)
                  for n, uri in sources)
    config = ServiceConfig(
        server=server, hub=from_args(HubSettings, args),
        capture=from_args(CaptureSettings, args), policy=from_args(SessionPolicy, args),
        sessions=specs, access=access,
        hub_url=hub_url(args), hub_prefix=hub_prefix(args),
        http_processors=tuple(dict.fromkeys(("auto", "truth", "tracker", "live",
                                             args.processor))),
        delegates=getattr(args, "delegate", True))

    import logging

    logging.basicConfig(level=config.server.log_level.upper(),
                        format="articast %(levelname)s: %(message)s")
    if names and not args.json:
        print(f"articast: starting {', '.join(names)}; the URL follows once the face streams",
              file=sys.stderr, flush=True)

    def listening(url: str, failed: dict[str, str]) -> None:
        http = url.replace("ws://", "http://", 1).rsplit("/ws", 1)[0]
        up = [n for n in names if n not in failed]  # never a URL for a failed session
        avatar = f"{http}/avatar/" + (f"?session={up[0]}" if up else "")
        if args.json:
            print(json.dumps({"url": url, "avatar": avatar, "sessions": up,
                              "failed": failed}), flush=True)
        else:
            first = up[0] if up else "NAME"
            if failed:
                print(f"articast: not serving {', '.join(failed)}: failed (the reason is "
                      "above)", file=sys.stderr, flush=True)
            print(f"articast: serving {', '.join(up) or 'no session yet'} at {url}\n"
                  f"  browser avatar: {avatar}\n"
                  f'  subscribe with {{"type": "subscribe", "session": "{first}"}}; '
                  "Ctrl-C stops", flush=True)
            if access.token:
                print("  this server needs its token: clients send 'Authorization: Bearer "
                      "TOKEN'; browsers add token=TOKEN to the avatar URL", flush=True)

    serve(config, listening)
    # Ctrl-C in a terminal ends as KeyboardInterrupt ("interrupted", cli.main); a SIGINT the
    # shell had us ignore (a background job) or a handled stop returns here: say so too
    print(f"articast {args.command}: stopped", file=sys.stderr, flush=True)
    return 0


def _serve(args: argparse.Namespace) -> int:
    from articast.service.sources import parse_named

    return _run(args, [parse_named(s) for s in args.source])


def _demo(args: argparse.Namespace) -> int:
    return _run(args, [("demo", f"synthetic:seed={args.seed}&fps={args.fps}&loop=yes")])


def _name(args: argparse.Namespace, path: Path) -> str:
    import re

    return args.name or re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem)[:64] or "replay"


def _plays(args: argparse.Namespace) -> str:
    if args.plays is not None:
        return f"plays={args.plays}"
    return "loop=yes" if args.loop else "loop=no"


def _replay(args: argparse.Namespace) -> int:
    from urllib.parse import quote

    span = "".join(f"&{k}={quote(v)}" for k, v in (("start", args.start), ("end", args.end))
                   if v)
    uri = f"file:{args.video}?pace={args.pace}&{_plays(args)}{span}"
    return _run(args, [(_name(args, args.video), uri)])


def _replay_record(args: argparse.Namespace) -> int:
    uri = f"replay-record:{args.recording}?pace={args.pace}&{_plays(args)}"
    return _run(args, [(_name(args, args.recording), uri)])


def _gateway(args: argparse.Namespace) -> int:
    from articast.service.app import ServiceConfig
    from articast.service.server import serve

    server = from_args(ServerSettings, args)
    url = hub_url(args, required=True)
    config = ServiceConfig(server=server, hub=from_args(HubSettings, args),
                           access=access_policy(args, server.host),
                           hub_url=url, hub_prefix=hub_prefix(args), role="gateway")

    def listening(ws_url: str, failed: dict[str, str]) -> None:
        if args.json:
            print(json.dumps({"url": ws_url, "hub": _safe_url(url)}), flush=True)
        else:
            print(f"articast gateway: serving the sessions of {_safe_url(url)} at {ws_url}; "
                  "Ctrl-C stops", flush=True)

    serve(config, listening)
    return 0


def _safe_url(url: str) -> str:
    """A Redis URL without its password (never printed)."""
    from urllib.parse import urlsplit, urlunsplit

    p = urlsplit(url)
    if p.password:
        netloc = f"{p.username or ''}:***@{p.hostname}" + (f":{p.port}" if p.port else "")
        return urlunsplit(p._replace(netloc=netloc))
    return url


def _track_worker(args: argparse.Namespace) -> int:
    import asyncio

    from articast.core.errors import InputError
    from articast.service.processors import check_processor
    from articast.service.sources import parse_named, parse_uri, probe
    from articast.service.worker import SessionSpec

    url = hub_url(args, required=True)
    sources = [parse_named(s) for s in args.source]
    if not sources:
        raise InputError("give at least one --source NAME=URI")
    names = [n for n, _ in sources]
    if len(set(names)) != len(names):
        raise InputError(f"session names must differ: {names}")
    for _, uri in sources:
        probe(uri)
        check_processor(args.processor, parse_uri(uri).kind,
                        bool(args.appearance or args.speaker))
    options = session_options(args)  # (a wrong speaker folder: one clear error now)
    specs = [SessionSpec(n, uri, args.model, args.appearance, args.camera, args.processor,
                         options=options, speaker=args.speaker)
             for n, uri in sources]
    from articast.service.worker_role import run_track_worker

    def started() -> None:
        if args.json:
            print(json.dumps({"hub": _safe_url(url), "sessions": names}), flush=True)
        else:
            print(f"articast track-worker: publishing {', '.join(names)} to {_safe_url(url)}; "
                  "Ctrl-C stops", flush=True)

    asyncio.run(run_track_worker(url, hub_prefix(args), specs,
                                 from_args(CaptureSettings, args),
                                 from_args(SessionPolicy, args), args.record or "", started))
    return 0
