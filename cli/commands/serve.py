"""``facecast serve``: run the streaming and rig service (facecast.server) under uvicorn.

Only maps flags onto ``Settings`` and starts the runner; server code is imported when
the command runs, never at ``facecast --help``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import TYPE_CHECKING

from facecast.cli.errors import CommandError

if TYPE_CHECKING:  # the server loads when the command runs, not for --help
    from collections.abc import Mapping

    from facecast.cli.commands import Subparsers
    from facecast.server.settings import Settings


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="run the server (REST rig API + WebSocket streaming)",
        description=(
            "Run the facecast server. Settings come from defaults < --config FILE (TOML) < "
            "FACECAST_* environment variables < these flags. Auth is on whenever --host is "
            "not a loopback address; the server refuses to start then without tokens."
        ),
    )
    parser.add_argument("--host", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="port to bind (default 8000)")
    parser.add_argument("--rigs", metavar="DIR", help="rig directory (default ./rigs)")
    parser.add_argument("--workers", type=int, help="worker processes (default 1)")
    parser.add_argument("--config", metavar="FILE", help="TOML config file (or FACECAST_CONFIG)")
    parser.add_argument(
        "--token",
        action="append",
        default=[],
        metavar="TOKEN[:ROLE+ROLE]",
        help="add an API token (roles admin, stream, publisher, viewer, performer or "
        "performer:NAME for one performer's profile only; default admin); repeatable",
    )
    parser.add_argument(
        "--auth",
        action="store_true",
        default=None,
        help="require tokens even on a loopback address",
    )
    parser.add_argument(
        "--redis",
        metavar="URL",
        help="Redis URL spanning broadcast channels across workers and hosts "
        "(or FACECAST_REDIS_URL; default: channels stay in this process)",
    )
    parser.add_argument("--log-level", choices=("debug", "info", "warning", "error"))
    parser.add_argument(
        "--ws",
        choices=("auto", "websockets-sansio", "websockets"),
        default="auto",
        help="uvicorn WebSocket implementation (auto: websockets-sansio)",
    )
    parser.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> Settings:
    """The ``Settings`` the flags, the config file and the environment describe."""
    from facecast.server.settings import Settings, parse_tokens

    overrides = {
        "host": args.host,
        "port": args.port,
        "rigs_dir": args.rigs,
        "workers": args.workers,
        "auth": args.auth,
        "log_level": args.log_level,
        "redis_url": getattr(args, "redis", None),
    }
    settings = Settings.load(config_file=args.config, env=env, overrides=overrides)
    if args.token:
        items = [t if ":" in t else f"{t}:admin" for t in args.token]
        extra = parse_tokens(",".join(items))
        settings = dataclasses.replace(settings, tokens={**settings.tokens, **extra})
    return settings


def run(args: argparse.Namespace) -> int:
    from facecast.server.runner import serve
    from facecast.server.settings import SettingsError

    try:
        settings = settings_from_args(args)
        settings.check_startable()
    except SettingsError as exc:
        raise CommandError(str(exc)) from None
    print(
        f"facecast: serving rigs from {settings.rigs_dir} on http://{settings.host}:"
        f"{settings.port} (auth {'on' if settings.auth_enabled else 'off'}, "
        f"{settings.workers} worker{'s' if settings.workers > 1 else ''}); docs at /docs",
        file=sys.stderr,
    )
    return serve(settings, ws=args.ws)
