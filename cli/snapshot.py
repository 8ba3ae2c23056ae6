"""Screenshot the web viewer playing the demo: ``python -m facecast.cli.snapshot --out docs/viewer.png``.

Starts a local server with the demo rig and drives Debian's Chromium through Playwright;
it never downloads a browser. Also the harness of the viewer tests (``serving``, ``launch``).
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = [
    "CHROMIUM_ARGS",
    "DEFAULT_CHROMIUM",
    "chromium_path",
    "launch",
    "main",
    "serving",
    "write_demo_rig",
]

#: Debian's chromium; FACECAST_CHROMIUM overrides it.
DEFAULT_CHROMIUM = "/usr/bin/chromium"
#: Headless Chromium without a GPU: WebGL through SwiftShader, nothing phoning home.
CHROMIUM_ARGS = (
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
)
DEMO_RIG_ID = "demo"


def chromium_path() -> str | None:
    """The Chromium executable to drive, or None when there is none."""
    path = os.environ.get("FACECAST_CHROMIUM", DEFAULT_CHROMIUM)
    return path if Path(path).is_file() and os.access(path, os.X_OK) else None


def launch(playwright: Any, executable: str | None = None) -> Any:
    """A headless Chromium browser (Playwright ``Browser``) from the system's executable."""
    executable = executable or chromium_path()
    if executable is None:
        raise FileNotFoundError(
            f"no Chromium at {DEFAULT_CHROMIUM} (install Debian's chromium or set "
            "FACECAST_CHROMIUM)"
        )
    return playwright.chromium.launch(
        executable_path=executable, headless=True, args=list(CHROMIUM_ARGS)
    )


def write_demo_rig(rigs_dir: Path, rig_id: str = DEMO_RIG_ID) -> Path:
    """Fit the procedural demo rig (tens of ms) and store it as ``rigs_dir/<rig_id>.rig``."""
    from facecast.rig import fit
    from facecast.rig.demo import demo_example_set

    rigs_dir.mkdir(parents=True, exist_ok=True)
    path = rigs_dir / f"{rig_id}.rig"
    fit(demo_example_set()).save(path)
    return path


@contextmanager
def serving(settings: Any, *, port: int = 0, startup_timeout: float = 10.0) -> Iterator[str]:
    """Serve the app with the viewer on 127.0.0.1:``port`` in a thread; yields its base URL.

    ``port`` 0 picks a free one; a given port is bound with SO_REUSEADDR, so a test can
    stop a server and start the next one on the same port at once.
    """
    from facecast.server.app import create_app
    from facecast.server.pages.viewer import mount_viewer
    from facecast.server.runner import ThreadedServer, uvicorn_config

    app = create_app(settings)
    if not any(getattr(route, "path", None) == "/viewer" for route in app.routes):
        mount_viewer(app, settings)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    port = sock.getsockname()[1]
    config = uvicorn_config(settings, app, host="127.0.0.1", port=port, log_level="warning")
    threaded = ThreadedServer(config, sock, startup_timeout=startup_timeout)
    while not threaded.started():
        time.sleep(0.01)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        threaded.stop()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m facecast.cli.snapshot",
        description="Screenshot the web viewer (or overlay) playing the demo performance.",
    )
    parser.add_argument("--out", type=Path, default=Path("docs/viewer.png"), help="PNG to write")
    parser.add_argument("--page", choices=("viewer", "overlay"), default="viewer")
    parser.add_argument("--width", type=int, default=960)
    parser.add_argument("--height", type=int, default=600)
    parser.add_argument(
        "--at", type=float, default=1.85, help="seconds into the demo performance to show"
    )
    parser.add_argument("--chromium", help=f"browser executable (default {DEFAULT_CHROMIUM})")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for frames")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("snapshot: needs playwright (pip install 'facecast[test]')", file=sys.stderr)
        return 2
    from facecast.server.settings import Settings

    with tempfile.TemporaryDirectory(prefix="facecast-snapshot-") as tmp:
        rigs = Path(tmp) / "rigs"
        write_demo_rig(rigs)
        with serving(Settings(rigs_dir=rigs, access_log=False)) as base, sync_playwright() as pw:
            browser = launch(pw, args.chromium)
            try:
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                errors: list[str] = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                # A short run-in from just before --at; the page reports which moment of
                # the performance it shows, so the picture is of that moment however
                # slowly the (software-rendering) browser goes.
                start = max(args.at - 0.3, 0.0)
                page.goto(f"{base}/{args.page}?rig={DEMO_RIG_ID}&start={start}")
                page.wait_for_function(
                    "at => (window.facecastStats.demoTime >= at && window.facecastStats.rendered"
                    " > 5) || window.facecastStats.error",
                    arg=args.at,
                    timeout=args.timeout * 1000,
                )
                failure = page.evaluate("() => window.facecastStats.error")
                if failure or errors:
                    print(f"snapshot: the page failed: {failure or errors[0]}", file=sys.stderr)
                    return 1
                args.out.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(args.out), omit_background=args.page == "overlay")
            finally:
                browser.close()
    print(f"snapshot: wrote {args.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
