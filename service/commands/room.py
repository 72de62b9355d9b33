"""``articast room`` and ``articast room-token``: the virtual meeting room (issue 41).

``articast room`` serves one room on loopback and prints its URL; each participant opens it,
gives a name, and joins with their camera and microphone (service/room.py, docs/ROOM.md).
``articast room-tracker ROOM --hub redis://…`` tracks the members of a room whose servers run
with ``--remote-trackers`` (their frames through Redis), on any machine that reaches the Redis
and shares the ``--speakers`` folder (service/room_tracker.py).
``articast room-token NAME`` prints the participant token (and URL) of NAME for the room
token in ARTICAST_ROOM_TOKEN or --room-token-file: how the host admits a participant whose
name is enrolled (their delegate shows their face: the room token alone cannot take it).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "room", help="a virtual meeting room: participants join from a browser and see each "
        "other as their delegates (one command, loopback)",
        description="Serve one meeting room and print its URL. Each participant opens the URL, "
        "gives a name and joins with their camera and microphone (WebRTC); every page shows "
        "every participant's delegate in one 3D scene, the one speaking highlighted, and plays "
        "the others' voices with their animation on the audio's clock. Nothing is recorded.")
    p.add_argument("name", nargs="?", default="room", help="the room's name (default room)")
    _token_arguments(p)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; a "
                   "camera page needs https:// beyond it: put a TLS proxy in front)")
    p.add_argument("--port", type=int, default=8765, help="port (default 8765; 0: any free)")
    p.add_argument("--speakers", type=Path, metavar="DIR",
                   help="enrolled speaker folders, one per participant name (DIR/NAME from "
                   "'articast enroll' or the page's guided enrolment): those participants "
                   "are tracked as themselves and shown as their own textured delegate; their "
                   "names need their participant token (default: a private folder under "
                   "$XDG_DATA_HOME or ~/.local/share/articast/rooms/NAME/speakers)")
    p.add_argument("--max-participants", type=int, default=8,
                   help="participants at once (default 8; each page receives that many "
                   "minus one audio tracks)")
    p.add_argument("--max-fps", type=float, default=15.0,
                   help="the most video frames a second each page sends (default 15: the "
                   "tracker takes 6-9 a second per participant on 2 busy cores; the media "
                   "process decodes every frame sent)")
    from articast.service.commands.serve import _hub_argument

    redis = p.add_argument_group(
        "more than one server", "With --hub redis://HOST:PORT/DB, several 'articast room' "
        "servers with the same room name and token serve one room: each holds the "
        "connections and trackers of the participants who joined on it, the membership and "
        "the tracked frames go through Redis (docs/ROOM.md).")
    _hub_argument(redis)
    redis.add_argument("--member-ttl", type=float, default=10.0, metavar="SECONDS",
                       help="with --hub: a member whose server stops refreshing their entry "
                       "(it died) leaves the room this long after (default 10)")
    redis.add_argument("--max-shared-delegate", type=float, default=4.0, metavar="MB",
                       help="with --hub: the largest enrolled delegate shared with the "
                       "room's other servers (default 4; one enrolled on the page is ~0.5): a "
                       "larger one is shown there as the generic head")
    redis.add_argument("--remote-trackers", action="store_true",
                       help="with --hub: track nobody here; the members' frames go to Redis "
                       "(JPEG, the newest 2 kept) and 'articast room-tracker ROOM' processes, "
                       "on any machine, track them")
    redis.add_argument("--tracker-wait", type=float, default=20.0, metavar="SECONDS",
                       help="with --remote-trackers: a member no tracker has taken for this "
                       "long is told so and leaves (default 20)")
    _running_arguments(p, "participants'")
    p.set_defaults(func=_room)

    r = sub.add_parser(
        "room-tracker", help="track the members of a room whose servers run with "
        "--remote-trackers (any machine that reaches its Redis)",
        description="Take members of ROOM (their frames in Redis, put there by the room's "
        "servers started with --remote-trackers), each under a lease another tracker takes "
        "over if this one dies, and track them as the room's servers would: their frames go "
        "to every server's pages through Redis. Run one or more, on any machine that reaches "
        "the Redis and shares the room's --speakers folder.")
    r.add_argument("room", help="the room's name (as given to 'articast room')")
    _hub_argument(r, required=True)
    r.add_argument("--speakers", type=Path, metavar="DIR",
                   help="the room's speakers folder, as given to 'articast room' (default: "
                   "its private one on this machine)")
    r.add_argument("--max-members", type=int, default=8,
                   help="members this tracker takes at most (default 8; each takes a core "
                   "while it tracks)")
    r.add_argument("--lease", type=float, default=6.0, metavar="SECONDS",
                   help="a member this tracker stops renewing (it died) is taken by another "
                   "this long after (default 6)")
    r.add_argument("--seed", type=int, default=1,
                   help="the built-in speaker model that tracks members without an enrolment "
                        "(its seed; default 1, as the room's servers)")
    _running_arguments(r, "members'")
    r.set_defaults(func=_room_tracker)

    t = sub.add_parser(
        "room-token", help="print a participant's token for a room (for enrolled names)",
        description="Print the participant token of NAME for the room token in "
        "ARTICAST_ROOM_TOKEN or --room-token-file, and the URL that joins with it.")
    t.add_argument("participant", help="the participant's name")
    _token_arguments(t)
    t.add_argument("--speakers", type=Path, metavar="DIR",
                   help="the room's speakers folder, as given to 'articast room' (default: "
                   "its private one): a participant who enrolled on the page has a token "
                   "bound to their folder")
    t.add_argument("--room", default="room",
                   help="the room's name (default room; where its private speakers folder is)")
    t.add_argument("--url", default="http://127.0.0.1:8765",
                   help="the room server's address (default http://127.0.0.1:8765)")
    t.set_defaults(func=_room_token)


def _running_arguments(p: argparse.ArgumentParser, whose: str) -> None:
    """What tracks the video, the start-up line's form and the log's level."""
    p.add_argument("--processor", default="auto",
                   help=f"what tracks the {whose} video: auto (the tracker, default), or "
                   "pkg.mod:callable (tests)")
    p.add_argument("--json", action="store_true", help="print the start-up line as JSON")
    p.add_argument("--log-level", default="warning", help="debug | info | warning (default)")


def _token_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--room-token-file", type=Path, metavar="FILE",
                   help="the room token (else env ARTICAST_ROOM_TOKEN; 'articast room' makes "
                   "one for this run when neither is given)")


def room_token(args: argparse.Namespace, required: bool) -> str:
    from articast.core.errors import InputError

    token = ""
    if args.room_token_file:
        try:
            token = args.room_token_file.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise InputError(f"--room-token-file {args.room_token_file}: "
                             f"{exc.strerror or exc}") from None
        if not token:
            raise InputError(f"--room-token-file {args.room_token_file}: empty")
    token = token or os.environ.get("ARTICAST_ROOM_TOKEN", "").strip()
    if not token and required:
        raise InputError("no room token: set ARTICAST_ROOM_TOKEN or --room-token-file FILE "
                         "(the one 'articast room' was started with)")
    if token and len(token) < 16:
        raise InputError("the room token is too short (16 characters or more: anyone who "
                         "guesses it joins)")
    return token


def _room(args: argparse.Namespace) -> int:
    import secrets

    from articast.core.errors import InputError
    from articast.service import webrtc
    from articast.service.session import NAME_RE

    reason = webrtc.missing()
    if reason:
        raise InputError(reason)
    if not NAME_RE.match(args.name):
        raise InputError(f"room name {args.name!r}: 1-64 of letters, digits, _ . -")
    if not 2 <= args.max_participants <= 32:
        raise InputError("--max-participants: 2 to 32")
    if not 1 <= args.max_fps <= 60:
        raise InputError("--max-fps: 1 to 60 frames a second")
    if not 1 <= args.member_ttl <= 3600:
        raise InputError("--member-ttl: 1 to 3600 s")
    if not 0.01 <= args.max_shared_delegate <= 64:
        raise InputError("--max-shared-delegate: 0.01 to 64 MB")
    if not 1 <= args.tracker_wait <= 3600:
        raise InputError("--tracker-wait: 1 to 3600 s")
    from articast.service.commands.serve import hub_prefix, hub_url

    hub = hub_url(args)
    if args.remote_trackers and not hub:
        raise InputError("--remote-trackers needs --hub redis://HOST:PORT/DB (the members' "
                         "frames go through it)")
    if args.speakers is not None and not args.speakers.is_dir():
        raise InputError(f"--speakers {args.speakers}: not a folder")
    from articast.service.room_enrol import default_speakers_dir, private_dir

    if args.speakers is None:  # the page's enrolments: private to this user
        try:
            args.speakers = private_dir(default_speakers_dir(args.name))
        except OSError as exc:
            raise InputError(f"cannot make the room's speakers folder "
                             f"{default_speakers_dir(args.name)}: {exc.strerror or exc} "
                             "(give one with --speakers DIR)") from None
    token = room_token(args, required=False)
    # the workers' fork server (which the media process and every tracker fork from) imports
    # what they need beside the server's own imports: the first offer does not wait for it
    from articast.service.worker import start_worker_server

    start_worker_server()
    made = not token
    token = token or secrets.token_urlsafe(24)

    from articast.service.app import ServiceConfig
    from articast.service.room import RoomConfig
    from articast.service.security import AccessPolicy
    from articast.service.server import serve
    from articast.service.settings import ServerSettings

    # the server's own token (session API, /ws) is the operator's: participants never get it
    operator = os.environ.get("ARTICAST_TOKEN", "") or secrets.token_urlsafe(24)
    config = ServiceConfig(
        server=ServerSettings(host=args.host, port=args.port, log_level=args.log_level),
        access=AccessPolicy(token=operator, bind_host=args.host),
        hub_url=hub, hub_prefix=hub_prefix(args),
        room=RoomConfig(name=args.name, token=token,
                        speakers=str(args.speakers.resolve()) if args.speakers else "",
                        max_participants=args.max_participants, processor=args.processor,
                        max_fps=args.max_fps, member_ttl_s=args.member_ttl,
                        max_shared_delegate=round(args.max_shared_delegate * 1e6),
                        remote_trackers=args.remote_trackers,
                        tracker_wait_s=args.tracker_wait, warm_media=True))

    import logging

    from articast.service.jsonsafe import dumps

    logging.basicConfig(level=args.log_level.upper(), format="articast %(levelname)s: %(message)s")

    def listening(url: str, failed: dict[str, str]) -> None:
        http = url.replace("ws://", "http://", 1).rsplit("/ws", 1)[0]
        page = f"{http}/room?room={token}"
        if args.json:
            print(dumps({"url": page, "room": args.name}), flush=True)
            return
        print(f"articast room {args.name}: open {page}\n  give a name and join; each "
              "participant opens the same URL. Ctrl-C ends the room.", flush=True)
        if made:
            print("  (a room token made for this run; to keep one, set ARTICAST_ROOM_TOKEN or "
                  "--room-token-file)", flush=True)

    serve(config, listening)
    print(f"articast room {args.name}: ended", file=sys.stderr, flush=True)
    return 0


def _room_tracker(args: argparse.Namespace) -> int:
    import asyncio
    import logging

    from articast.core.errors import InputError
    from articast.service.commands.serve import _safe_url, hub_prefix, hub_url
    from articast.service.session import NAME_RE

    if not NAME_RE.match(args.room):
        raise InputError(f"room name {args.room!r}: 1-64 of letters, digits, _ . -")
    if not 1 <= args.max_members <= 64:
        raise InputError("--max-members: 1 to 64")
    if not 1 <= args.lease <= 600:
        raise InputError("--lease: 1 to 600 s")
    url = hub_url(args, required=True)
    if args.speakers is not None and not args.speakers.is_dir():
        raise InputError(f"--speakers {args.speakers}: not a folder")
    from articast.service.room_enrol import default_speakers_dir

    speakers = args.speakers or default_speakers_dir(args.room)
    from articast.service.worker import start_worker_server

    start_worker_server()
    logging.basicConfig(level=args.log_level.upper(),
                        format="articast %(levelname)s: %(message)s")
    from articast.service.room_tracker import run_room_tracker

    def started() -> None:
        if args.json:
            from articast.service.jsonsafe import dumps

            print(dumps({"hub": _safe_url(url), "room": args.room, "pid": os.getpid()}),
                  flush=True)
        else:
            print(f"articast room-tracker: tracking room {args.room}'s members from "
                  f"{_safe_url(url)}; Ctrl-C stops", flush=True)

    asyncio.run(run_room_tracker(url, hub_prefix(args), args.room,
                                 str(Path(speakers).resolve()) if Path(speakers).is_dir()
                                 else "", args.processor, args.seed, args.lease,
                                 args.max_members, started=started))
    return 0


def _room_token(args: argparse.Namespace) -> int:
    from articast.core.errors import InputError
    from articast.service.room import participant_token
    from articast.service.session import NAME_RE

    if not NAME_RE.match(args.participant):
        raise InputError(f"participant name {args.participant!r}: 1-64 of letters, digits, "
                         "_ . -")
    from articast.service.room_enrol import Enrolments, default_speakers_dir

    token = room_token(args, required=True)
    speakers = args.speakers or default_speakers_dir(args.room)
    secret = Enrolments(speakers).secret(args.participant)
    ptoken = participant_token(token, args.participant, secret)
    print(f"{ptoken}\n{args.url.rstrip('/')}/room?key={ptoken}")
    return 0
