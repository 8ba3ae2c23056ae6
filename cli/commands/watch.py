"""``facecast watch``: record what a viewer of a broadcast channel receives into a file.

Maps flags onto the bridges' `watch_channel` (PROTOCOL.md §2.1 ``.../watch``) and writes
like ``facecast clone`` (.npz with weights/vertices plus seq and t); no cloning here.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from facecast.cli.commands._animation import write_results
from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "watch",
        help="record a broadcast channel as one character (a viewer's results)",
        description=(
            "Watch channel CHANNEL on rig NAME and write the results received to OUT: .npz "
            "(weights, or vertices in vertices mode; names, fps, seq, t), or .glb / "
            "an OBJ folder like `facecast clone`. Stops after --frames results, when the "
            "publisher leaves after having been live, or on Ctrl-C."
        ),
    )
    parser.add_argument("url", metavar="URL", help="server base URL, e.g. http://127.0.0.1:8000")
    parser.add_argument("channel", metavar="CHANNEL", help="channel name")
    parser.add_argument("--rig", required=True, metavar="NAME", help="rig id to watch on")
    parser.add_argument("-o", "--out", required=True, metavar="OUT", help=".npz, .glb or folder")
    parser.add_argument("--frames", type=int, metavar="N", help="stop after N results")
    parser.add_argument("--output", choices=("weights", "vertices"), default="weights")
    parser.add_argument("--dtype", choices=("f32", "f16"), default="f32")
    parser.add_argument("--timeout", type=float, default=0.0, metavar="S",
                        help="stop after S seconds (default: no limit)")  # fmt: skip
    parser.add_argument("--token", help="API token with the viewer role (default: FACECAST_TOKEN)")
    parser.set_defaults(func=run)


async def record(args: argparse.Namespace) -> dict[str, Any]:
    """Results as lists (values, seq, t) plus the ``ready``; stops as documented."""
    import asyncio

    from facecast.client.channel import channel_url, watch_channel
    from facecast.protocol import ChannelIdle, ChannelLive, Error, Ready, Result

    query = {"rig": args.rig, "output": args.output, "dtype": args.dtype}
    url = channel_url(args.url, args.channel, "watch", query)
    # "error": the server's last non-fatal error to this watcher (a frame that does not
    # fit the rig watched), said if no result comes.
    got: dict[str, Any] = {"ready": None, "values": [], "seq": [], "t": [], "error": None}
    was_live = False

    async def consume() -> None:
        nonlocal was_live
        stream = watch_channel(url, token=args.token)
        try:
            async for message in stream:
                if isinstance(message, Ready):
                    got["ready"] = got["ready"] or message
                elif isinstance(message, ChannelLive):
                    was_live = True
                elif isinstance(message, ChannelIdle) and was_live:
                    return
                elif isinstance(message, Error):
                    got["error"] = message
                elif isinstance(message, Result):
                    got["values"].append(message.values)
                    got["seq"].append(message.seq)
                    got["t"].append(message.ts)
                    if args.frames and len(got["values"]) >= args.frames:
                        return
        finally:
            await stream.aclose()

    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(args.timeout or None):
            await consume()
    return got


def run(args: argparse.Namespace) -> int:
    import asyncio

    import numpy as np

    from facecast.client.connection import ConnectionFailed

    out = Path(args.out)
    if not out.parent.exists():
        raise CommandError(f"{out.parent}: no such folder for {out.name}")
    if args.frames is not None and args.frames < 1:
        raise CommandError(f"--frames must be >= 1, got {args.frames}")
    try:
        got = asyncio.run(record(args))
    except KeyboardInterrupt:
        got = None
    except (ValueError, ConnectionFailed) as exc:
        raise CommandError(str(exc)) from None
    if not got or not got["values"]:
        error = got["error"] if got else None
        cause = ""
        if error is not None:
            code = getattr(error.code, "name", str(error.code)).lower()
            cause = f": the server said {code}: {error.message}"
            if code == "wrong_point_count":
                cause += (
                    " (rig_mismatch: the publisher's frames have another number of feature "
                    f"points than rig {args.rig!r}; watch on a rig of the same source, e.g. "
                    "one fitted from a character file for a publisher on the generic ARKit set)"
                )
        raise CommandError(f"no result received from channel {args.channel!r}{cause}")
    values = np.stack(got["values"]).astype(np.float32)
    ready = got["ready"]
    seq = np.asarray(got["seq"], dtype=np.int64)
    t = np.asarray(got["t"], dtype=np.float64)
    steps = np.diff(t)
    steps = steps[steps > 0]
    fps = float(1.0 / np.median(steps)) if steps.size else 60.0
    if out.suffix.lower() == ".npz":
        arrays = {"names": np.asarray(ready.names, dtype=str),
                  "fps": np.asarray(fps, dtype=np.float64), "seq": seq, "t": t}  # fmt: skip
        arrays["weights" if args.output == "weights" else "vertices"] = values
        np.savez(out, allow_pickle=False, **arrays)  # no record is an object array
    else:
        from facecast.client.fetch import fetch_rig

        rig = fetch_rig(args.url, args.rig, token=args.token)
        write_results(out, rig, args.output, values, fps)
    print(f"facecast watch: {len(seq)} results (seq {seq[0]}..{seq[-1]}) -> {out}", file=sys.stderr)
    return 0
