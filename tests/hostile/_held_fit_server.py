"""``facecast serve``'s own ``serve()`` with its fit pool held by a parse that never ends.

Run by test_hostile_shutdown as ``python -m tests.hostile._held_fit_server RIGS PORT``: once
the server is up, the app's fit pool is given work that blocks (a stand-in for the longest
parse or fit an upload can cause, which no limit makes shorter than a shutdown should
take), and ``held`` is printed when it has begun, ``queued`` when an upload's work has
been queued behind it. Everything else is the real server.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from fastapi import FastAPI

import facecast.server.runner as runner
from facecast.server.settings import Settings

#: How long the held work blocks: far beyond the 2 s a shutdown may take.
HOLD_SECONDS = 60.0


def main() -> int:
    rigs, port = Path(sys.argv[1]), int(sys.argv[2])
    made: list[FastAPI] = []
    factory = runner.create_app

    def create_app(settings: Settings) -> FastAPI:
        made.append(factory(settings))
        return made[-1]

    runner.create_app = create_app  # the same app, kept in reach

    def hold() -> None:
        print("held", flush=True)
        threading.Event().wait(HOLD_SECONDS)

    def occupy() -> None:
        while not (made and hasattr(made[0].state, "fit_executor")):
            threading.Event().wait(0.01)  # lifespan start-up: no event to wait on
        pool = made[0].state.fit_executor
        pool.submit(hold)
        submit = pool.submit

        def submit_said(fn, /, *args, **kwargs):  # type: ignore[no-untyped-def]
            future = submit(fn, *args, **kwargs)
            print("queued", flush=True)  # an upload read whole, behind the held work
            return future

        pool.submit = submit_said

    threading.Thread(target=occupy, daemon=True).start()
    settings = Settings(host="127.0.0.1", port=port, rigs_dir=rigs, log_level="info")
    return runner.serve(settings)


if __name__ == "__main__":
    sys.exit(main())
