"""The hostile-client limits are settings: named, validated, from TOML, env and flags alike."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from facecast.cli.main import main
from facecast.server.runner import uvicorn_config
from facecast.server.settings import Settings, SettingsError

SERVER_MD = Path(__file__).resolve().parents[2] / "server" / "SERVER.md"

POSITIVE = (
    "request_idle_timeout",
    "request_head_timeout",
    "max_pending_connections",
    "max_pong_backlog",
    "refuse_timeout",
    "ws_close_timeout",
)
NON_NEGATIVE = ("max_connections_per_token", "max_connections_per_address", "publisher_slots")


@pytest.mark.parametrize("name", POSITIVE)
def test_a_time_or_size_limit_must_be_positive(name):
    with pytest.raises(SettingsError, match=name):
        Settings(**{name: 0})


@pytest.mark.parametrize("name", NON_NEGATIVE)
def test_a_quota_may_be_zero_for_none_but_not_negative(name):
    assert getattr(Settings(**{name: 0}), name) == 0
    with pytest.raises(SettingsError, match=name):
        Settings(**{name: -1})


def test_the_limits_come_from_the_environment():
    env = {"FACECAST_MAX_PENDING_CONNECTIONS": "7", "FACECAST_MAX_CONNECTIONS_PER_ADDRESS": "3"}
    settings = Settings.load(env=env)

    assert (settings.max_pending_connections, settings.max_connections_per_address) == (7, 3)


def _documented_limit() -> tuple[int, int]:
    """SERVER.md's rule for uvicorn's ``limit_concurrency``: (HTTP headroom, default)."""
    row = next(
        line for line in SERVER_MD.read_text().splitlines()
        if line.startswith("| uvicorn's `limit_concurrency` |")
    )  # fmt: skip
    found = re.search(r"`publisher_slots` \+ (\d+) \+ `max_pending_connections` \((\d+)\)", row)
    assert found is not None, row
    return int(found[1]), int(found[2])


def test_pending_connections_get_room_of_their_own_in_uvicorns_limit():
    settings = Settings(max_connections=10, publisher_slots=2, max_pending_connections=30)
    config = uvicorn_config(settings, app=None)
    headroom, default = _documented_limit()

    # As documented: sessions, publisher slots, HTTP requests beyond them, pending ones.
    assert config.limit_concurrency == 10 + 2 + headroom + 30
    assert uvicorn_config(Settings(), app=None).limit_concurrency == default
    assert config.timeout_keep_alive == settings.request_idle_timeout


@pytest.mark.parametrize("ws", ["wsproto", "none"])
def test_a_websocket_implementation_the_server_cannot_bound_is_refused(ws):
    with pytest.raises(SettingsError, match="not supported"):
        uvicorn_config(Settings(), app=None, ws=ws)


def test_serve_does_not_offer_wsproto_which_is_not_installed(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["serve", "--ws", "wsproto"])

    assert exc.value.code == 2
    assert "invalid choice: 'wsproto'" in capsys.readouterr().err
