"""``facecast bridge``: connect trackers and avatar apps to a broadcast channel.

``bridge livelink`` receives Live Link Face UDP and publishes points to a channel,
``bridge ifacialmocap`` the same for iFacialMocap / Facemotion3D; ``bridge vmc``
watches a channel's weights and sends VMC OSC. Only argument parsing and wiring here; the loops live in facecast.cli.bridges, imported when a command runs.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # the bridges and the client load when a command runs, not for --help
    from collections.abc import Awaitable, Callable, Coroutine
    from typing import Any, TypeVar

    import numpy as np

    from facecast.cli.bridges.tracker import BridgeStats, DatagramReceiver, HeadSink
    from facecast.cli.commands import Subparsers
    from facecast.client.channel import FramePublisher
    from facecast.rig.sources.source_rig import SourceRig

    ReceiverT = TypeVar("ReceiverT", bound=DatagramReceiver[Any])
    #: ``run_bridge(receiver, source_rig, publisher, on_head)``: one tracker's loop.
    BridgeLoop = Callable[
        [ReceiverT, SourceRig, FramePublisher, HeadSink | None], Awaitable[BridgeStats]
    ]


def _host_port(text: str, default_port: int | None = None) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, "" if default_port is None else str(default_port)
    host = host.strip("[]")
    try:
        number = int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}") from None
    if not host or not 0 <= number <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT with a port 0-65535, got {text!r}")
    return host, number


def _phone(text: str) -> tuple[str, int | None]:
    if text.count(":") == 1 or text.startswith("["):
        return _host_port(text)
    return text, None


def _send(text: str) -> tuple[str, int]:
    return _host_port(text, 39539)


def _add_tracker_arguments(parser: argparse.ArgumentParser, port: int, why: str) -> None:
    """The options of a tracker bridge in: --source-rig, --listen, --head-pose, --vmc-head."""
    parser.add_argument(
        "--source-rig",
        default="generic",
        metavar="PATH",
        help="the ARKit-named shapes that turn the tracker's weights into points: 'generic' "
        "(the default: facecast's generic ARKit set, which characters uploaded as files are "
        "paired with), an example set (e.g. from 'facecast import ict-facekit') or ICT archive",
    )
    parser.add_argument(
        "--listen",
        type=lambda text: _host_port(text, port),
        default=("0.0.0.0", port),
        metavar="HOST:PORT",
        help=f"UDP address to receive on (default 0.0.0.0:{port}, {why})",
    )
    parser.add_argument(
        "--head-pose",
        action="store_true",
        help="apply the packets' head yaw/pitch/roll to the points (the session then "
        "asks the server to align them away again); the head rotation goes out as each "
        "frame's head pose either way",
    )
    parser.add_argument(
        "--vmc-head",
        type=_send,
        metavar="HOST:PORT",
        help="also send each frame's head rotation as VMC /VMC/Ext/Bone/Pos Head straight "
        "to this receiver; not to one that 'bridge vmc' feeds, which gets the head "
        "through the channel already",
    )
    parser.add_argument(
        "--vmc-head-position",
        type=_vector,
        default=(0.0, 0.0, 0.0),
        metavar="X,Y,Z",
        help="the head bone's local position sent with --vmc-head (metres, Unity frame; "
        "default 0,0,0, for receivers that apply bone rotations only)",
    )


def _vector(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z (three finite numbers), got {text!r}")
    return values[0], values[1], values[2]


def _mapping(text: str) -> tuple[str, str]:
    name, sep, target = text.partition("=")
    if not sep or not name or not target:
        raise argparse.ArgumentTypeError(f"expected NAME=VMCNAME, got {text!r}")
    return name, target


def _add_bridge(
    sub: Subparsers,
    name: str,
    *,
    help: str,
    description: str,
    url_help: str,
    channel_help: str,
    rig_help: str,
) -> argparse.ArgumentParser:
    """A bridge's sub-parser, opened with the channel it bridges: URL, --channel, --rig."""
    parser = sub.add_parser(name, help=help, description=description)
    parser.add_argument("url", metavar="URL", help=url_help)
    parser.add_argument("--channel", required=True, help=channel_help)
    parser.add_argument("--rig", required=True, help=rig_help)
    return parser


def _add_run_arguments(
    parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], int]
) -> None:
    """The options every bridge ends with (--token, --frames), and ``run`` to run it."""
    parser.add_argument("--token", help="bearer token (default FACECAST_TOKEN)")
    parser.add_argument("--frames", type=int, metavar="N", help="stop after N frames")
    parser.set_defaults(func=run)


def _bridge_url(args: argparse.Namespace, kind: str, query: dict[str, str] | None = None) -> str:
    """The channel's ``publish`` or ``watch`` URL; a malformed URL or name is a CommandError."""
    from facecast.client.channel import channel_url

    try:
        return channel_url(args.url, args.channel, kind, query)
    except ValueError as exc:
        raise CommandError(str(exc)) from None


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "bridge",
        help="bridge Live Link Face / iFacialMocap into a channel, or a channel out to VMC",
        description="Bridges between facecast broadcast channels and outside tools.",
    )
    sub = parser.add_subparsers(dest="bridge", metavar="BRIDGE", required=True)

    ll = _add_bridge(
        sub,
        "livelink",
        help="receive Live Link Face UDP and publish the points to a channel",
        description=(
            "Receive Live Link Face packets (iPhone app, UDP), turn the 52 ARKit weights "
            "into feature points through a source rig, and publish them to a channel. "
            "Point the app's Live Link target at this machine's --listen address."
        ),
        url_help="server base URL, e.g. http://127.0.0.1:8000",
        channel_help="channel to publish to",
        rig_help="rig id on the server (its K must match)",
    )
    _add_tracker_arguments(ll, 11111, "the app's default port")
    ll.add_argument("--subject", help="only this Live Link subject name")
    _add_run_arguments(ll, run_livelink)

    ifm = _add_bridge(
        sub,
        "ifacialmocap",
        help="receive iFacialMocap / Facemotion3D UDP and publish the points to a channel",
        description=(
            "Receive iFacialMocap or Facemotion3D frames (iPhone apps, UDP text "
            "'name-value|...', values 0-100), turn the ARKit weights into feature points "
            "through a source rig, and publish them to a channel. With --phone, ask the "
            "app to stream here (again whenever nothing arrives for 2 s)."
        ),
        url_help="server base URL, e.g. http://127.0.0.1:8000",
        channel_help="channel to publish to",
        rig_help="rig id on the server (its K must match)",
    )
    _add_tracker_arguments(ifm, 49983, "where both apps stream")
    ifm.add_argument(
        "--phone",
        type=_phone,
        metavar="HOST[:PORT]",
        help="the iPhone's address: send it the app's start request (port: the app's, "
        "49983 for iFacialMocap, 49993 for Facemotion3D)",
    )
    ifm.add_argument(
        "--app",
        choices=("ifacialmocap", "facemotion3d"),
        default="ifacialmocap",
        help="which app --phone runs (its request and port; default ifacialmocap)",
    )
    _add_run_arguments(ifm, run_ifacialmocap)

    vmc = _add_bridge(
        sub,
        "vmc",
        help="watch a channel's weights and send them as VMC (OSC) blend shapes",
        description=(
            "Watch a channel on a rig and send every result as VMC protocol OSC "
            "(/VMC/Ext/Blend/Val, /VMC/Ext/Blend/Apply, /VMC/Ext/OK) to an avatar app, "
            "and the publisher's head pose, when its frames carry one, as /VMC/Ext/Bone/Pos "
            "Head."
        ),
        url_help="server base URL",
        channel_help="channel to watch",
        rig_help="rig whose weights to receive",
    )
    vmc.add_argument(
        "--send",
        type=_send,
        default=("127.0.0.1", 39539),
        metavar="HOST:PORT",
        help="VMC receiver (default 127.0.0.1:39539)",
    )
    vmc.add_argument(
        "--map",
        type=_mapping,
        action="append",
        default=[],
        metavar="NAME=VMCNAME",
        help="send rig expression NAME as VMCNAME (repeatable; over --names)",
    )
    vmc.add_argument(
        "--names",
        choices=("vrm0", "vrm1", "perfectsync"),
        default="vrm0",
        help="how the receiver spells expressions: vrm0 (default, VSeeFace: VRM 0.x presets "
        "A/Joy/Blink_L, ARKit names in Perfect Sync PascalCase), vrm1 (aa/happy/blinkLeft), "
        "perfectsync (every ARKit name as its Perfect Sync clip, eyeBlinkLeft -> EyeBlinkLeft)",
    )
    vmc.add_argument(
        "--max-datagram",
        type=int,
        default=1400,
        metavar="BYTES",
        help="split each frame into OSC bundles of at most BYTES (default 1400: no IP "
        "fragmentation on a 1500-byte MTU; 576-65507)",
    )
    vmc.add_argument("--no-clamp", action="store_true", help="send weights outside [0, 1] too")
    _add_run_arguments(vmc, run_vmc)


def _run_tracker(
    args: argparse.Namespace,
    what: str,
    open_receiver: Callable[[], Awaitable[ReceiverT]],
    run_bridge: BridgeLoop[ReceiverT],
    *,
    start: Callable[[ReceiverT], Coroutine[Any, Any, None]] | None = None,
) -> int:
    """Open the receiver, publish what ``run_bridge`` makes of it, report; shared by trackers.

    ``open_receiver()`` makes the receiver; ``run_bridge(receiver, source_rig, publisher,
    on_head)`` runs the loop; ``start(receiver)``, if given, runs beside it (and is
    cancelled when the loop returns).
    """
    import asyncio

    from facecast.cli.bridges.vmc import VmcSender, vmc_head_bundle
    from facecast.client.channel import FramePublisher
    from facecast.client.connection import ConnectionFailed
    from facecast.protocol import Hello
    from facecast.rig.sources.layouts import load_layout
    from facecast.rig.sources.source_rig import load_source_rig, names_generic_set

    source_rig = load_source_rig(args.source_rig)
    if source_rig.missing:
        print(
            f"facecast bridge: the source rig has no shape for {', '.join(source_rig.missing)}; "
            "those weights are ignored",
            file=sys.stderr,
        )
    url = _bridge_url(args, "publish")
    hello = Hello(rig=args.rig, align=args.head_pose)

    async def main() -> int:
        receiver = await open_receiver()
        head_sender = None if args.vmc_head is None else VmcSender(*args.vmc_head)
        helper: asyncio.Task[None] | None = None
        try:
            async with FramePublisher(url, hello, token=args.token) as publisher:
                assert publisher.ready is not None
                k = publisher.ready.num_points
                rig_points = source_rig
                if names_generic_set(args.source_rig) and load_layout().takes_first(
                    source_rig.num_points, k
                ):
                    # A rig fitted on the layout's earlier version (24 or 20 points): the
                    # generic set's first k, as /perform sends such a rig.
                    rig_points = source_rig.first(k)
                if k != rig_points.num_points:
                    raise CommandError(
                        f"rig {args.rig!r} needs K={k} points, the source rig makes "
                        f"{rig_points.num_points}"
                    )
                host, port = receiver.address
                print(
                    f"facecast bridge: {what} on udp://{host}:{port} -> channel "
                    f"{args.channel!r} (rig {args.rig}, K={rig_points.num_points})",
                    file=sys.stderr,
                )
                if start is not None:
                    helper = asyncio.create_task(start(receiver))

                def send_head(head: np.ndarray) -> None:
                    assert head_sender is not None
                    head_sender.send(vmc_head_bundle(head, args.vmc_head_position))

                on_head = None if head_sender is None else send_head
                stats = await run_bridge(receiver, rig_points, publisher, on_head)
                last = receiver.last_error
                print(
                    f"facecast bridge: {stats.published} frames published, "
                    f"{publisher.stats.dropped} dropped, {receiver.malformed} bad packets"
                    + (f" (last: {last.code}: {last})" if last is not None else "")
                    + (
                        ""
                        if head_sender is None
                        else f"; VMC head {head_sender.sent} sent, {head_sender.failed} failed"
                    ),
                    file=sys.stderr,
                )
        except ConnectionFailed as exc:
            raise CommandError(str(exc)) from None
        finally:
            if helper is not None:
                helper.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await helper
            receiver.close()
            if head_sender is not None:
                head_sender.close()
        return 0

    return asyncio.run(main())


def run_livelink(args: argparse.Namespace) -> int:
    from facecast.cli.bridges.livelink import (
        LiveLinkReceiver,
        open_livelink_receiver,
        run_livelink_bridge,
    )

    def run_bridge(
        receiver: LiveLinkReceiver,
        source_rig: SourceRig,
        publisher: FramePublisher,
        on_head: HeadSink | None,
    ) -> Awaitable[BridgeStats]:
        return run_livelink_bridge(
            receiver,
            source_rig,
            publisher,
            head_pose=args.head_pose,
            subject=args.subject,
            on_head=on_head,
            max_frames=args.frames,
        )

    return _run_tracker(args, "Live Link", lambda: open_livelink_receiver(*args.listen), run_bridge)


def run_ifacialmocap(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.cli.bridges.ifacialmocap import (
        FacialMocapReceiver,
        open_ifacialmocap_receiver,
        request_stream,
    )
    from facecast.cli.bridges.tracker import run_tracker_bridge

    def run_bridge(
        receiver: FacialMocapReceiver,
        source_rig: SourceRig,
        publisher: FramePublisher,
        on_head: HeadSink | None,
    ) -> Awaitable[BridgeStats]:
        return run_tracker_bridge(
            receiver,
            source_rig,
            publisher,
            head_pose=args.head_pose,
            on_head=on_head,
            max_frames=args.frames,
        )

    async def keep_requesting(receiver: FacialMocapReceiver) -> None:
        # The app streams once asked; ask again while nothing arrives (it restarted,
        # the phone slept). A timer, not a wait for an event: there is none to wait on.
        while True:
            if time.monotonic() - receiver.last_datagram > 2.0:
                try:
                    request_stream(receiver, args.phone[0], args.app, args.phone[1])
                except OSError as exc:
                    print(f"facecast bridge: cannot reach {args.phone[0]}: {exc}", file=sys.stderr)
            await asyncio.sleep(1.0)

    return _run_tracker(
        args,
        "iFacialMocap" if args.app == "ifacialmocap" else "Facemotion3D",
        lambda: open_ifacialmocap_receiver(*args.listen),
        run_bridge,
        start=None if args.phone is None else keep_requesting,
    )


def run_vmc(args: argparse.Namespace) -> int:
    import asyncio

    from facecast.cli.bridges.vmc import MIN_DATAGRAM, VmcSender, run_vmc_bridge
    from facecast.client.channel import watch_channel
    from facecast.client.connection import ConnectionFailed

    if not MIN_DATAGRAM <= args.max_datagram <= 65507:
        raise CommandError(
            f"--max-datagram must be in [{MIN_DATAGRAM}, 65507] bytes, got {args.max_datagram}"
        )
    url = _bridge_url(args, "watch", {"rig": args.rig, "output": "weights"})

    async def main() -> int:
        with VmcSender(*args.send) as sender:
            print(
                f"facecast bridge: channel {args.channel!r} on rig {args.rig} -> VMC "
                f"udp://{args.send[0]}:{args.send[1]}",
                file=sys.stderr,
            )
            try:
                stats = await run_vmc_bridge(
                    watch_channel(url, token=args.token),
                    sender,
                    convention=args.names,
                    overrides=dict(args.map),
                    clamp=not args.no_clamp,
                    max_datagram=args.max_datagram,
                    max_frames=args.frames,
                )
            except (ConnectionFailed, ValueError) as exc:  # ValueError: names VMC cannot carry
                raise CommandError(str(exc)) from None
            print(
                f"facecast bridge: {stats.frames} frames sent as VMC ({args.names} names), "
                f"{sender.sent} datagrams sent, {sender.failed} failed"
                + (f" (last: {sender.last_error})" if sender.last_error else ""),
                file=sys.stderr,
            )
        return 0

    return asyncio.run(main())
