"""The server's one typed configuration object: defaults < TOML file < FACECAST_* env < CLI.

Built once at start-up and passed down explicitly; nothing here is read at import time
and no other module reads the environment or the config file.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import json
import os
import tomllib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any
from urllib.parse import urlsplit

from .errors import SettingsError
from .names import valid_name

__all__ = [
    "PERFORMER_ROLE",
    "ROLES",
    "Settings",
    "SettingsError",
    "bound_performer",
    "normalise_origin",
    "parse_tokens",
]

#: The roles a token can hold; ``admin`` implies all others (see ``auth``). ``performer``
#: may store calibration captures and refit rigs on them (server/SERVER.md, "Performers").
ROLES = frozenset({"admin", "stream", "publisher", "viewer", "performer"})
#: ``performer:NAME`` (a role of its own): the performer role for the performer NAME
#: only; a token may hold several. Plain ``performer`` is the role for every name.
PERFORMER_ROLE = "performer"

ENV_PREFIX = "FACECAST_"
MiB = 1024 * 1024


@dataclass(frozen=True)
class Settings:
    """Everything the server can be told, with every limit named.

    Sizes are in bytes, durations in seconds, rates in frames per second.
    """

    # -- where to listen and what to serve ---------------------------------------------
    host: str = "127.0.0.1"
    port: int = 8000
    rigs_dir: Path = Path("rigs")
    workers: int = 1

    # -- auth -----------------------------------------------------------------------------
    #: token -> roles. Read from ``[tokens]`` in the config file or ``FACECAST_TOKENS``.
    #: Besides ``ROLES``, ``performer:NAME`` binds the token to the performer NAME.
    tokens: Mapping[str, frozenset[str]] = field(
        default_factory=lambda: MappingProxyType({}), repr=False
    )
    #: Force auth on for a loopback address; it is always on for any other address.
    auth: bool = False
    #: Whether ``/metrics`` needs an admin token when auth is on (as every endpoint but
    #: ``/healthz`` and ``/readyz`` does); false opens it to tokenless scrapers.
    metrics_auth: bool = True

    # -- uploads --------------------------------------------------------------------------
    max_upload_bytes: int = 64 * MiB
    max_extracted_bytes: int = 256 * MiB
    max_archive_members: int = 2000
    #: Largest character file stored (the GLB as kept: a .gltf folder's packed into one);
    #: a larger one is 422 ``character_too_large`` before it is fitted. Downloads stream
    #: from disk in chunks whatever the size; this bounds the disk each character takes.
    max_character_bytes: int = 64 * MiB
    #: Largest allowed (total uncompressed size / archive size): zip-bomb guard.
    max_compression_ratio: float = 200.0
    #: Fits (and rig uploads) waiting or running at once; more get 503 ``server_busy``.
    max_pending_fits: int = 4
    #: Seconds a request body (upload, capture) may take to arrive in all; a slower one
    #: is 408 ``body_timeout``, so a trickled body cannot hold an upload slot for long.
    body_timeout: float = 120.0
    fit_threads: int = 1
    #: Uploads up to this size (and performer captures) are parsed and fitted in a lane of
    #: their own (one thread, ``fit_threads`` do the rest): a small upload or a
    #: calibration never queues behind a large file's parse. 0: one lane for all.
    small_upload_bytes: int = 1 * MiB
    #: Fit slots (of ``max_pending_fits``) one token without the admin role may hold at
    #: once; one more is 429 ``too_many_fits``. 0: no per-token cap.
    max_fits_per_token: int = 1

    # -- character files (glTF, GLB, VRM; rig/io/gltf_check.py) ---------------------------
    #: The most an uploaded character (PUT /v1/characters/{id}, with or without
    #: ``expressions=transfer``) may declare, checked before anything is allocated; one
    #: more is 422 ``gltf_exceeds_limits`` naming the setting. JSON values (objects,
    #: arrays, strings, numbers) in its JSON, counted before it is parsed.
    max_gltf_json_values: int = 1_000_000
    #: Nodes, and levels of the node tree (a root alone is 1): the nodes must form a tree.
    max_gltf_nodes: int = 20_000
    max_gltf_depth: int = 256
    #: Meshes, and primitives of all meshes together.
    max_gltf_meshes: int = 1_000
    max_gltf_primitives: int = 10_000
    #: Vertices (every distinct POSITION accessor) and triangles (every primitive's) of
    #: all meshes together: a fit holds 24 bytes a vertex and 12 a triangle beside the
    #: body, its morph targets and its basis. Over ten times the heaviest avatars published
    #: (a VRoid model ~30,000 vertices; VRChat ranks 70,000 triangles "Very Poor"); at
    #: 1 M and 2 M an upload could cost 3.7x max_upload_bytes (docs/characters.md "What a
    #: file may declare", SERVER.md "What an upload can cost the server").
    max_gltf_vertices: int = 500_000
    max_gltf_faces: int = 1_000_000
    #: Morph targets of one mesh, and morph targets x vertices summed over the meshes
    #: (reading them allocates 12 bytes each; quantised ones count twice, read as float64;
    #: 4 M: 52 ARKit targets on a 76,000-vertex face), with VRM expressions mixing morphs x
    #: the face's vertices (twice: float64), and expressions paired x the face's vertices
    #: (each a row of the fit's float32 basis).
    max_gltf_morph_targets: int = 1_000
    max_gltf_morph_values: int = 4_000_000
    #: Values (count x components) of all accessors together, with or without a bufferView
    #: (one without is all zeros, which a few bytes can declare); meshopt views decode to at
    #: most 4 bytes each (128 MB: twice max_upload_bytes; at 64 M one 4 MB upload decoded
    #: 256 MB, 3.9x). A face at max_gltf_morph_values with morph normals is ~26 M.
    max_gltf_accessor_values: int = 32_000_000

    # -- deformation transfer jobs (server/http/transfer.py) ------------------------------
    #: Largest character face mesh (vertices) ``PUT /v1/characters/{id}?expressions=transfer``
    #: takes; a larger one is 422 ``too_many_vertices``. 35,000 (was 50,000) holds the job's
    #: memory to the uploads' bound, 3x max_upload_bytes + 4 MiB (SERVER.md, "What an upload
    #: can cost the server": its sparse factors grow faster than the face, +233 MB at 48,972
    #: vertices), over eight times a VRoid face mesh (4,083) and twice ICT's head (14,062).
    #: One transfer runs per server at a time; another is 503 ``transfer_busy``.
    max_transfer_vertices: int = 35_000
    #: Its largest face mesh in triangles (a closed mesh has about twice as many as
    #: vertices); a larger one is 422 ``too_many_faces``.
    max_transfer_faces: int = 105_000
    #: Finished transfer job records kept under ``<rigs_dir>/.jobs``; older ones are pruned
    #: (a character's record also goes when the character is deleted or replaced).
    max_job_records: int = 64
    #: ICT-FaceKit (its folder or ``ict_facekit.npz``), the expressions a transfer carries:
    #: "" looks in ``$FACECAST_ICT`` and ``../shared/data/ict-facekit``; "off" turns
    #: transfers off. Without it a transfer is 503 ``transfer_unavailable``.
    transfer_source: str = ""

    # -- performers (server/http/performers.py) -------------------------------------------
    #: Largest calibration capture body (JSON or msgpack points per expression).
    max_capture_bytes: int = 1 * MiB

    # -- streaming ------------------------------------------------------------------------
    max_connections: int = 200
    #: Per-connection frame rate limit (token bucket refill rate).
    max_fps: float = 240.0
    #: Token bucket depth: frames a client may send in a burst above ``max_fps``.
    rate_burst: int = 60
    #: Calibrations a connection may ask for per second on average (``calibrate`` with
    #: points, or without: its next frame), and at once: each refits the rig's projection
    #: (~1 ms of CPU, and on a channel once per watched rig), so one over the budget is
    #: refused with RATE_LIMITED (``calibrate_rate.py``; SERVER.md, the cost table).
    calibrate_rate: float = 1.0
    calibrate_burst: int = 4
    #: A session with no message from the client for this long is closed (IDLE_TIMEOUT).
    idle_timeout: float = 60.0
    max_message_bytes: int = 1 * MiB
    #: WebSocket-level ping interval and timeout (uvicorn keepalive); 0 disables.
    ping_interval: float = 20.0
    ping_timeout: float = 20.0
    #: Threads cloning frames for all sessions of one worker process.
    clone_threads: int = 2
    #: Loaded rigs kept in memory per worker process.
    rig_cache_size: int = 16

    # -- hostile clients (SERVER.md, "What a client without a token can cost the server") --
    #: Seconds a TCP connection may stay silent before its request (after it opened, or
    #: after its previous response); it is then closed. Also uvicorn's keep-alive timeout.
    request_idle_timeout: float = 5.0
    #: Seconds from a request's first byte to its complete head (request line and headers);
    #: a slower one (slowloris) is closed.
    request_head_timeout: float = 10.0
    #: Connections open without a request in progress (not yet sent, or idle between
    #: requests); one more closes the oldest of them, so they cannot fill the server.
    max_pending_connections: int = 256
    #: Bytes of pongs the server may queue for a WebSocket client that does not read
    #: (a ping flood) before it cuts the connection.
    max_pong_backlog: int = 64 * 1024
    #: Seconds the server waits for a WebSocket client's part of the closing handshake
    #: before it drops the connection (uvicorn's own wait is 10 s).
    ws_close_timeout: float = 2.0
    #: Seconds a refused WebSocket connection may take in all (wait for its first
    #: message, the error, the close) before it is cut, whatever the peer does.
    refuse_timeout: float = 3.0
    #: WebSocket connections (stream, publish, watch) one token may hold at once (with
    #: auth on); 0: no per-token limit.
    max_connections_per_token: int = 100
    #: WebSocket connections one client address may hold at once; 0: no limit. Behind
    #: a reverse proxy every client has the proxy's address unless ``trusted_proxies``
    #: names it.
    max_connections_per_address: int = 100
    #: Addresses or networks (``10.0.0.0/8``) of reverse proxies whose ``X-Forwarded-For``
    #: and ``X-Forwarded-Proto`` are believed (uvicorn's ``forwarded_allow_ips``); ``"*"``:
    #: any peer. Empty (the default): none, so a client cannot name its own address and
    #: dodge ``max_connections_per_address`` (uvicorn alone trusts 127.0.0.1).
    trusted_proxies: tuple[str, ...] = ()
    #: Connections that only channel publishers may take beyond ``max_connections``, and
    #: beyond each token's and each address's quota, so watchers (or streams) filling the
    #: server, one token's quota or one address's cannot lock the performer out.
    publisher_slots: int = 4

    # -- broadcast channels (server/channels/) ----------------------------------------------
    #: Redis URL spanning channels across processes (``redis://host:6379/0``); empty:
    #: channels live in this process only.
    redis_url: str = ""
    #: Seconds without a frame from a connected publisher before watchers get face_lost.
    face_lost_after: float = 0.5
    #: Seconds over which a lost face eases from the last pose to the neutral.
    face_lost_ease: float = 1.0

    # -- browsers (server/guards/origins.py) -----------------------------------------------
    #: Origins (``scheme://host[:port]``) besides the server's own whose pages may open
    #: WebSockets and send PUT/DELETE here, and read the REST API (CORS): a viewer page
    #: served elsewhere that points here with ``server=``. ``"*"``: any origin.
    allowed_origins: tuple[str, ...] = ()
    #: Host names a loopback-bound server answers to besides loopback names and ``host``
    #: (a reverse proxy's public name); ``"*"``: any (no Host check).
    allowed_hosts: tuple[str, ...] = ()

    # -- operations -----------------------------------------------------------------------
    #: Seconds open sessions get to close (1001) on SIGTERM before they are cut.
    shutdown_timeout: float = 5.0
    log_level: str = "info"
    access_log: bool = True
    #: Time each stage of every stream frame and count blend batch sizes for /metrics
    #: (``facecast_stage_*``, ``facecast_blend_batches``; ~1 µs a frame). The
    #: benchmarks turn it on to attribute their figures.
    stage_timing: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "rigs_dir", Path(self.rigs_dir))
        tokens = {str(k): frozenset(v) for k, v in dict(self.tokens).items()}
        object.__setattr__(self, "tokens", MappingProxyType(tokens))
        for token, roles in tokens.items():
            if not token:
                raise SettingsError("tokens: an empty token is not allowed")
            unknown = {r for r in roles if r not in ROLES and bound_performer(r) is None}
            if unknown:
                raise SettingsError(
                    f"tokens: unknown role(s) {sorted(unknown)}; roles are {sorted(ROLES)} "
                    f"and {PERFORMER_ROLE}:NAME (NAME a performer name)"
                )
            if not roles:
                raise SettingsError("tokens: every token needs at least one role")
            if PERFORMER_ROLE in roles and any(bound_performer(r) for r in roles):
                raise SettingsError(
                    f"tokens: a token holds both '{PERFORMER_ROLE}' (every performer) and "
                    f"'{PERFORMER_ROLE}:NAME' (one performer); keep the one you mean"
                )
        if not 0 <= self.port <= 65535:
            raise SettingsError(f"port: {self.port} is not in 0..65535")
        positive = (
            "workers",
            "max_upload_bytes",
            "max_extracted_bytes",
            "max_archive_members",
            "max_character_bytes",
            "max_compression_ratio",
            "max_pending_fits",
            "body_timeout",
            "fit_threads",
            "max_capture_bytes",
            "max_transfer_vertices",
            "max_transfer_faces",
            "max_gltf_json_values",
            "max_gltf_nodes",
            "max_gltf_depth",
            "max_gltf_meshes",
            "max_gltf_primitives",
            "max_gltf_vertices",
            "max_gltf_faces",
            "max_gltf_morph_targets",
            "max_gltf_morph_values",
            "max_gltf_accessor_values",
            "max_job_records",
            "max_connections",
            "max_fps",
            "rate_burst",
            "calibrate_rate",
            "calibrate_burst",
            "idle_timeout",
            "max_message_bytes",
            "clone_threads",
            "rig_cache_size",
            "face_lost_after",
            "face_lost_ease",
            "request_idle_timeout",
            "request_head_timeout",
            "max_pending_connections",
            "max_pong_backlog",
            "refuse_timeout",
            "ws_close_timeout",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise SettingsError(f"{name}: must be > 0, got {getattr(self, name)!r}")
        for name in (
            "ping_interval",
            "ping_timeout",
            "shutdown_timeout",
            "max_connections_per_token",
            "max_connections_per_address",
            "publisher_slots",
            "max_fits_per_token",
            "small_upload_bytes",
        ):
            if getattr(self, name) < 0:
                raise SettingsError(f"{name}: must be >= 0, got {getattr(self, name)!r}")
        origins = []
        for origin in self.allowed_origins:
            try:
                origins.append(origin if origin == "*" else normalise_origin(origin))
            except ValueError as exc:
                raise SettingsError(f"allowed_origins: {exc}") from None
        object.__setattr__(self, "allowed_origins", tuple(origins))
        for name in self.allowed_hosts:
            if name != "*" and (not name or any(c in name for c in "/:[] ")):
                raise SettingsError(
                    f"allowed_hosts: expected host names without port, got {name[:80]!r}"
                )
        object.__setattr__(self, "allowed_hosts", tuple(n.lower() for n in self.allowed_hosts))
        for proxy in self.trusted_proxies:
            try:
                if proxy != "*":
                    ipaddress.ip_network(proxy, strict=False)
            except ValueError:
                raise SettingsError(
                    f"trusted_proxies: expected IP addresses or networks, got {proxy[:80]!r}"
                ) from None
        if self.redis_url and not self.redis_url.startswith(("redis://", "rediss://", "unix://")):
            raise SettingsError(
                "redis_url: expected redis://host:port[/db], rediss://... or unix://...; "
                f"got {self.redis_url[:60]!r}"
            )

    # -- derived ------------------------------------------------------------------------
    @property
    def auth_enabled(self) -> bool:
        """Auth is on for any non-loopback bind address, and when forced with ``auth``."""
        return self.auth or not is_loopback(self.host)

    def check_startable(self) -> None:
        """Raise ``SettingsError`` for a configuration the server must refuse to start with."""
        if self.auth_enabled and not self.tokens:
            why = "--auth was given" if is_loopback(self.host) else f"host {self.host} is public"
            raise SettingsError(
                f"auth is on ({why}) but no API tokens are configured: add a [tokens] table "
                'to the config file (e.g. "secret" = ["admin"]) or set '
                "FACECAST_TOKENS=token:admin,token2:stream+viewer"
            )

    # -- building -----------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        *,
        config_file: str | os.PathLike[str] | None = None,
        env: Mapping[str, str] | None = None,
        overrides: Mapping[str, Any] | None = None,
    ) -> Settings:
        """Merge defaults < TOML config file < ``FACECAST_*`` env < ``overrides`` (CLI).

        ``config_file`` defaults to ``FACECAST_CONFIG`` from ``env``. ``None`` values in
        ``overrides`` mean "not given" and are skipped.
        """
        env = os.environ if env is None else env
        values: dict[str, Any] = {}
        path = config_file if config_file is not None else env.get(f"{ENV_PREFIX}CONFIG")
        if path:
            values.update(_read_toml(Path(path)))
        values.update(_from_env(env))
        values.update({k: v for k, v in (overrides or {}).items() if v is not None})
        return cls.from_mapping(values, source="settings")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], *, source: str) -> Settings:
        """Build from plain values (strings are converted to each field's type)."""
        hints = typing.get_type_hints(cls)
        known = {f.name for f in dataclasses.fields(cls)}
        kwargs: dict[str, Any] = {}
        for name, value in values.items():
            if name not in known:
                raise SettingsError(f"{source}: unknown setting {name!r}")
            kwargs[name] = _coerce(name, hints[name], value, source)
        try:
            return cls(**kwargs)
        except TypeError as exc:  # pragma: no cover - guarded by the known-name check
            raise SettingsError(f"{source}: {exc}") from None

    def to_json(self) -> str:
        """Serialise for handing to worker processes (see ``runner``)."""
        data: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "tokens":
                value = {k: sorted(v) for k, v in value.items()}
            elif isinstance(value, Path):
                value = str(value)
            data[f.name] = value
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str) -> Settings:
        return cls.from_mapping(json.loads(text), source="serialised settings")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bound_performer(role: str) -> str | None:
    """NAME for a ``performer:NAME`` role (NAME a valid performer name), else None."""
    prefix, sep, name = role.partition(":")
    return name if sep and prefix == PERFORMER_ROLE and valid_name(name) else None


def _roles(text: str) -> frozenset[str]:
    return frozenset(r.strip() for r in text.split("+") if r.strip())


def parse_tokens(text: str) -> dict[str, frozenset[str]]:
    """Parse ``"tok1:admin,tok2:stream+viewer,tok3:performer:ann+publisher"`` into ``{token: roles}``.

    A token may contain ``:``: it ends at the last ``:`` after which only roles follow,
    ``performer:NAME`` included (so ``tok:performer:ann`` is ``tok`` bound to ann, and
    ``a:b:viewer`` the token ``a:b``). With no such ``:`` it ends at the last one, and
    ``Settings`` names the unknown role.
    """
    tokens: dict[str, frozenset[str]] = {}
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        token, sep, roles = item.rpartition(":")
        if not sep or not token:
            raise SettingsError(
                f"FACECAST_TOKENS: expected 'token:role[+role...]', got an item without ':'"
                f" (item {len(tokens) + 1})"
            )
        splits = [i for i, c in enumerate(item) if c == ":" and i > 0]
        for i in reversed(splits):
            held = _roles(item[i + 1 :])
            if held and all(r in ROLES or bound_performer(r) for r in held):
                token, roles = item[:i], item[i + 1 :]
                break
        tokens[token] = _roles(roles)
    return tokens


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise SettingsError(f"config file {path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"config file {path}: not valid TOML ({exc})") from None
    if "tokens" in data:
        tokens = data["tokens"]
        if not isinstance(tokens, dict) or not all(
            isinstance(v, list) and all(isinstance(r, str) for r in v) for v in tokens.values()
        ):
            raise SettingsError(
                f'config file {path}: [tokens] must map token strings to role lists, e.g. "s" = ["admin"]'
            )
        data["tokens"] = {k: frozenset(v) for k, v in tokens.items()}
    return data


def _from_env(env: Mapping[str, str]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    names = {f.name for f in dataclasses.fields(Settings)}
    for key, raw in env.items():
        if not key.startswith(ENV_PREFIX) or key == f"{ENV_PREFIX}CONFIG":
            continue
        name = key[len(ENV_PREFIX) :].lower()
        if name == "tokens":
            values["tokens"] = parse_tokens(raw)
        elif name in names:
            values[name] = raw
    return values


def _coerce(name: str, hint: Any, value: Any, source: str) -> Any:
    if name == "tokens":
        if isinstance(value, str):
            return parse_tokens(value)
        if not isinstance(value, Mapping):
            raise SettingsError(f"{source}: tokens must be a table of token -> roles")
        return value
    try:
        if hint is bool:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in {"1", "true", "yes", "on"}:
                return True
            if text in {"0", "false", "no", "off", ""}:
                return False
            raise ValueError(f"not a boolean: {value!r}")
        if hint is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(f"not an integer: {value!r}")
            return int(value)
        if hint is float:
            if isinstance(value, bool):
                raise ValueError(f"not a number: {value!r}")
            return float(value)
        if hint == tuple[str, ...]:
            # TOML arrays, or "a,b" from the environment.
            items = value.split(",") if isinstance(value, str) else value
            if not isinstance(items, list | tuple) or not all(isinstance(i, str) for i in items):
                raise ValueError(f"not a list of strings: {value!r}")
            return tuple(i.strip() for i in items if i.strip())
        if hint is Path:
            return Path(value)
        if hint is str:
            if not isinstance(value, str):
                raise ValueError(f"not a string: {value!r}")
            return value
    except (TypeError, ValueError) as exc:
        raise SettingsError(f"{source}: {name}: {exc}") from None
    return value  # pragma: no cover - every field type is handled above


def normalise_origin(origin: str) -> str:
    """``scheme://host[:port]`` in lower case, default ports dropped; ValueError otherwise."""
    parts = urlsplit(origin.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"expected http(s)://host[:port], got {origin[:80]!r}")
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
        raise ValueError(f"an origin has no path, query or user: {origin[:80]!r}")
    port = parts.port  # ValueError for a bad port
    host = parts.hostname if ":" not in parts.hostname else f"[{parts.hostname}]"
    default = {"http": 80, "https": 443}[parts.scheme]
    return f"{parts.scheme}://{host}" + ("" if port in (None, default) else f":{port}")
