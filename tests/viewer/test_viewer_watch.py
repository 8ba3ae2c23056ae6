"""The overlay watching a broadcast channel (PROTOCOL.md §2.1) that a real publisher
streams the demo into."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from websockets.sync.client import connect

from facecast.cli.snapshot import serving
from facecast.protocol import (
    PUBLISH_PATH,
    SUBPROTOCOL,
    Frame,
    Hello,
    Ready,
    decode_server,
    encode,
)
from facecast.rig.demo import demo_animation

from .test_viewer_pages import FRAMES, changed_fraction, frames, pixels


@contextmanager
def publishing(base_url: str, channel: str, token: str | None = None) -> Iterator[None]:
    """Stream the demo performance into ``channel`` from a thread until the block exits.

    ``token``: presented as the bearer subprotocol (a server with auth on).
    """
    points = demo_animation(seconds=4.0, with_vertices=False).points.astype("float32")
    stop = threading.Event()
    ready = threading.Event()
    url = base_url.replace("http", "ws") + PUBLISH_PATH.format(name=channel)

    def run() -> None:
        protocols = [SUBPROTOCOL] if token is None else [SUBPROTOCOL, f"facecast.bearer.{token}"]
        with connect(url, subprotocols=protocols) as ws:
            ws.send(encode(Hello(rig="demo")))
            assert isinstance(decode_server(ws.recv(timeout=10)), Ready)
            ready.set()
            seq = 0
            # Lockstep (send, wait for the result) at the performance's 60 fps: never
            # ahead of the server and under its rate limit.
            while not stop.wait(1 / 60):
                ws.send(encode(Frame(seq=seq, ts=seq / 60, points=points[seq % len(points)])))
                ws.recv(timeout=10)
                seq += 1

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert ready.wait(10), "the publisher got no ready"
    try:
        yield
    finally:
        stop.set()
        thread.join(10)


def test_overlay_animates_from_a_watched_channel(settings, page):
    with serving(settings) as base_url:
        page.goto(f"{base_url}/overlay?channel=stage&rig=demo")
        page.wait_for_function("['idle', 'live'].includes(window.facecastStats.state)")
        with publishing(base_url, "stage"):
            page.wait_for_function(FRAMES, arg=3)
            first = pixels(page.screenshot(omit_background=True))
            page.wait_for_function(FRAMES, arg=frames(page) + 10)
            second = pixels(page.screenshot(omit_background=True))

    assert changed_fraction(first, second) > 0.002
    assert page.errors == []
