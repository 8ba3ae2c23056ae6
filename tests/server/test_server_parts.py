"""The server's parts without HTTP: settings precedence, the rig store, archive extraction."""

from __future__ import annotations

import io
import subprocess
import sys
import tarfile
import threading
from pathlib import Path

import pytest
from _server_helpers import tiny_example_set, zip_bytes
from hypothesis import HealthCheck, assume, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from facecast.rig import RigFileError, fit
from facecast.server.settings import Settings, SettingsError, parse_tokens
from facecast.server.storage.archive import (
    MAX_NAME_BYTES,
    MAX_PATH_BYTES,
    ArchiveError,
    ArchiveLimits,
    extract_archive,
)
from facecast.server.storage.jobs import JOBS_DIR
from facecast.server.storage.rig_store import SCRATCH_DIR, RigNotFoundError, RigStore

# -- settings -----------------------------------------------------------------------------


def test_precedence_is_defaults_then_file_then_env_then_cli(tmp_path):
    config = tmp_path / "facecast.toml"
    config.write_text(
        'port = 9001\nmax_fps = 30.0\nlog_level = "debug"\n[tokens]\n"a" = ["admin"]\n'
    )
    env = {"FACECAST_PORT": "9002", "FACECAST_MAX_FPS": "60", "FACECAST_TOKENS": "b:viewer"}

    settings = Settings.load(config_file=config, env=env, overrides={"port": 9003, "host": None})

    assert settings.port == 9003  # CLI beats env beats file
    assert settings.max_fps == 60.0  # env beats file
    assert settings.log_level == "debug"  # file beats default
    assert settings.host == "127.0.0.1"  # None means "flag not given"
    assert dict(settings.tokens) == {"b": frozenset({"viewer"})}  # env replaces file tokens


def test_config_file_may_come_from_the_environment(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("max_connections = 7\n")

    settings = Settings.load(env={"FACECAST_CONFIG": str(config)})

    assert settings.max_connections == 7


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("nonsense = 1\n", "unknown setting 'nonsense'"),
        ("port = 'x'\n", "port"),
        ("max_fps = 0\n", "max_fps: must be > 0"),
        ("[tokens]\n'a' = ['root']\n", "unknown role"),
        ("port = \n", "not valid TOML"),
    ],
)
def test_bad_config_is_a_settings_error_naming_the_setting(tmp_path, content, message):
    config = tmp_path / "c.toml"
    config.write_text(content)

    with pytest.raises(SettingsError, match=message):
        Settings.load(config_file=config, env={})


def test_env_tokens_parse_roles_joined_with_plus():
    assert parse_tokens("t1:admin, t2:stream+viewer") == {
        "t1": frozenset({"admin"}),
        "t2": frozenset({"stream", "viewer"}),
    }
    with pytest.raises(SettingsError):
        parse_tokens("no-roles-here")


def test_a_token_is_bound_to_performers_in_toml_the_environment_or_a_flag(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('[tokens]\n"ann" = ["performer:ann", "publisher", "viewer"]\n')
    roles = frozenset({"performer:ann", "publisher", "viewer"})

    from_file = Settings.load(config_file=config, env={})
    from_env = Settings.load(env={"FACECAST_TOKENS": "ann:performer:ann+publisher+viewer"})

    assert dict(from_file.tokens) == dict(from_env.tokens) == {"ann": roles}
    assert Settings.from_json(from_file.to_json()).tokens == from_file.tokens
    # A token may contain ':': it ends where only roles follow.
    assert parse_tokens("a:b:performer:bob+performer:cy,c:d:viewer") == {
        "a:b": frozenset({"performer:bob", "performer:cy"}),
        "c:d": frozenset({"viewer"}),
    }


@pytest.mark.parametrize(
    ("roles", "message"),
    [
        (["performer:"], "unknown role"),
        (["performer:no spaces"], "unknown role"),
        (["viewer:ann"], "unknown role"),
        (["performer", "performer:ann"], "keep the one you mean"),
    ],
)
def test_a_bad_performer_binding_is_a_settings_error(tmp_path, roles, message):
    with pytest.raises(SettingsError, match=message):
        Settings(rigs_dir=tmp_path, tokens={"t": frozenset(roles)})


def test_allowed_origins_and_hosts_come_from_toml_or_the_environment(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('allowed_origins = ["https://Viewer.Example:443", "http://a.example:81"]\n')

    from_file = Settings.load(config_file=config, env={})
    from_env = Settings.load(
        env={
            "FACECAST_ALLOWED_ORIGINS": "http://b.example,*",
            "FACECAST_ALLOWED_HOSTS": "Proxy.Example",
        }
    )

    assert from_file.allowed_origins == ("https://viewer.example", "http://a.example:81")
    assert from_env.allowed_origins == ("http://b.example", "*")
    assert from_env.allowed_hosts == ("proxy.example",)
    assert Settings.from_json(from_file.to_json()).allowed_origins == from_file.allowed_origins


@pytest.mark.parametrize(
    "values",
    [
        {"allowed_origins": ("viewer.example",)},  # no scheme
        {"allowed_origins": ("ftp://viewer.example",)},
        {"allowed_origins": ("http://viewer.example/page",)},
        {"allowed_origins": ("http://viewer.example:99999",)},
        {"allowed_hosts": ("proxy.example:8000",)},
        {"allowed_hosts": ("",)},
    ],
)
def test_bad_allowed_origins_or_hosts_are_refused_naming_the_setting(values):
    name = next(iter(values))

    with pytest.raises(SettingsError, match=name):
        Settings(**values)


def test_settings_survive_the_json_trip_to_worker_processes(tmp_path):
    settings = Settings(rigs_dir=tmp_path, port=0, tokens={"x": {"stream"}}, idle_timeout=2.5)

    assert Settings.from_json(settings.to_json()) == settings


# -- store ----------------------------------------------------------------------------------


@pytest.fixture
def store(tmp_path) -> RigStore:
    s = RigStore(tmp_path / "rigs")
    s.open()
    return s


def _rig_dir_entries(store: RigStore) -> list[str]:
    """What the rig directory holds besides the store's scratch folder, which must be empty
    but for its lock: no temp file left behind."""
    leftovers = [p.name for p in store.scratch.iterdir() if p.name != ".lock"]
    assert leftovers == []
    # The store's own folders: scratch, and .jobs (its change lock, job records).
    return sorted(
        p.name for p in store.directory.iterdir() if p.name not in (SCRATCH_DIR, JOBS_DIR)
    )


def test_concurrent_writes_of_one_id_leave_one_whole_rig(store, rig):
    other = fit(tiny_example_set(seed=5))
    blobs = [rig.to_bytes(), other.to_bytes()] * 8
    barrier = threading.Barrier(len(blobs))

    def put(data: bytes) -> None:
        barrier.wait()
        store.put_bytes("same", data)

    threads = [threading.Thread(target=put, args=(b,)) for b in blobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()

    assert store.get("same").checksum in {rig.checksum, other.checksum}
    assert _rig_dir_entries(store) == ["same.rig"]


def test_another_process_replacing_a_rig_is_seen_through_the_cache(tmp_path, rig):
    other = fit(tiny_example_set(seed=3))
    worker_a = RigStore(tmp_path)
    worker_b = RigStore(tmp_path)  # as a second worker process would have
    worker_a.put_rig("face", rig)
    assert worker_b.get("face").checksum == rig.checksum

    worker_a.put_rig("face", other)

    assert worker_b.get("face").checksum == other.checksum


def test_cached_rig_is_reused_while_the_file_is_unchanged(store, rig):
    store.put_rig("face", rig)

    assert store.get("face") is store.get("face")


def test_deleted_rig_is_gone_for_other_workers_too(tmp_path, rig):
    worker_a, worker_b = RigStore(tmp_path), RigStore(tmp_path)
    worker_a.put_rig("face", rig)
    worker_b.get("face")

    worker_a.delete("face")

    with pytest.raises(RigNotFoundError):
        worker_b.get("face")


def test_invalid_rig_bytes_write_nothing(store):
    with pytest.raises(RigFileError):
        store.put_bytes("bad", b"PK\x03\x04 not really")

    assert _rig_dir_entries(store) == []


def test_stale_temp_files_of_killed_writers_are_removed_at_open(tmp_path):
    import os

    directory = tmp_path / "rigs"
    directory.mkdir()
    stale = directory / ".tmp-face-abc"
    stale.write_bytes(b"half a rig")
    os.utime(stale, (0, 0))

    RigStore(directory).open()

    assert not stale.exists()


_KILLED_STORE = (
    "import sys\n"
    "from pathlib import Path\n"
    "from facecast.server.storage.rig_store import RigStore\n"
    "store = RigStore(Path(sys.argv[1]))\n"
    "store.open()\n"
    "(store.scratch / 'upload-abc').mkdir()\n"
    "(store.scratch / 'upload-abc' / 'facecast.toml').write_text('[source]')\n"
    "(store.scratch / 'face-123.rig').write_bytes(b'half a rig')\n"
    "print(store.scratch, flush=True)\n"
    "sys.stdin.read()  # until killed\n"
)


def test_scratch_of_a_killed_process_is_removed_at_the_next_open_and_live_ones_kept(tmp_path):
    directory = tmp_path / "rigs"
    live = RigStore(directory)
    live.open()
    (live.scratch / "upload-live").mkdir()
    child = subprocess.Popen(
        [sys.executable, "-c", _KILLED_STORE, str(directory)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    dead = Path(child.stdout.readline().strip())
    child.kill()  # SIGKILL: no cleanup of its own
    child.wait(10)
    child.stdin.close()
    child.stdout.close()
    assert (dead / "upload-abc").is_dir() and (dead / "face-123.rig").is_file()

    RigStore(directory).open()

    assert not dead.exists()
    assert (live.scratch / "upload-live").is_dir()


def test_a_closed_store_leaves_no_scratch_behind(tmp_path, rig):
    store = RigStore(tmp_path / "rigs")
    store.open()
    store.put_rig("face", rig)
    scratch = store.scratch

    store.close()

    assert not scratch.exists()
    assert sorted(p.name for p in (tmp_path / "rigs").iterdir()) == [
        JOBS_DIR,  # the change lock's file
        SCRATCH_DIR,
        "face.rig",
    ]


# -- archives -------------------------------------------------------------------------------

LIMITS = ArchiveLimits(max_members=50, max_extracted_bytes=1 << 20, max_compression_ratio=100.0)

_name_part = st.sampled_from(["a", "b", "..", ".", "", "c.txt", "/", "C:", "\\", "x\x00y"])


@hsettings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(parts=st.lists(_name_part, min_size=1, max_size=5), as_tar=st.booleans())
def test_any_member_name_lands_inside_the_folder_or_is_refused(tmp_path_factory, parts, as_tar):
    name = "/".join(parts)
    assume(name)  # neither format can even store an empty name
    # The folder sits deep enough in a sandbox of its own that any climb out of it (at
    # most 5 ".." parts) still lands in the sandbox, which is what is searched for
    # strays: not the session's whole temporary tree, whose search grew with every test
    # before this one (25 s of a CI run).
    outside = tmp_path_factory.mktemp("sandbox")
    dest = outside.joinpath("1", "2", "3", "4", "5", "dest")
    dest.mkdir(parents=True)
    before = set(outside.rglob("*"))
    if as_tar:
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as archive:
            info = tarfile.TarInfo(name)
            info.size = 2
            archive.addfile(info, io.BytesIO(b"hi"))
        data = buffer.getvalue()
    else:
        data = zip_bytes({name: b"hi"})

    try:
        extract_archive(data, dest, LIMITS)
    except ArchiveError as exc:
        assert exc.code in {"unsafe_archive_member", "bad_archive", "duplicate_archive_member"}
    created = set(outside.rglob("*")) - before
    assert all(Path(p).is_relative_to(dest) for p in created)


def _deep(total: int) -> str:
    """A member path of exactly ``total`` bytes, in names of at most 220."""
    names = [200] * 4 + [total - 4 - 800]
    return "/".join("d" * n for n in names)


@pytest.mark.parametrize(
    ("name", "ok"),
    [
        ("n" * MAX_NAME_BYTES, True),
        ("n" * (MAX_NAME_BYTES + 1), False),
        ("é" * 128, False),  # 128 characters, 256 bytes: the limit is in bytes
        (_deep(MAX_PATH_BYTES), True),
        (_deep(MAX_PATH_BYTES + 1), False),
    ],
    ids=["name-255", "name-256", "name-256-bytes", "path-1024", "path-1025"],
)
@pytest.mark.parametrize("as_tar", [False, True])
def test_member_names_and_paths_are_bounded_in_bytes(tmp_path, name, ok, as_tar):
    if as_tar:
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w", format=tarfile.PAX_FORMAT) as archive:
            info = tarfile.TarInfo(name)
            info.size = 2
            archive.addfile(info, io.BytesIO(b"hi"))
        data = buffer.getvalue()
    else:
        data = zip_bytes({name: b"hi"})

    if ok:
        extract_archive(data, tmp_path, LIMITS)
        assert (tmp_path / name).read_bytes() == b"hi"
    else:
        with pytest.raises(ArchiveError) as info:
            extract_archive(data, tmp_path, LIMITS)
        assert (info.value.status, info.value.code) == (400, "archive_member_name_too_long")


@pytest.mark.parametrize("as_tar", [False, True])
@pytest.mark.parametrize("order", [("x", "x/y"), ("x/y", "x"), ("x", "x/")])
def test_a_file_and_a_folder_of_one_name_are_a_conflict_not_a_crash(tmp_path, order, as_tar):
    if as_tar:
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as archive:
            for member in order:
                info = tarfile.TarInfo(member.rstrip("/"))
                if member.endswith("/"):
                    info.type = tarfile.DIRTYPE
                else:
                    info.size = 1
                archive.addfile(info, None if member.endswith("/") else io.BytesIO(b"1"))
        data = buffer.getvalue()
    else:
        data = zip_bytes({member: b"" if member.endswith("/") else b"1" for member in order})

    with pytest.raises(ArchiveError) as info:
        extract_archive(data, tmp_path, LIMITS)
    assert (info.value.status, info.value.code) == (400, "archive_member_conflict")


def test_tar_symlink_and_hardlink_members_are_refused(tmp_path):
    for kind in (tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.CHRTYPE, tarfile.FIFOTYPE):
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as archive:
            info = tarfile.TarInfo("facecast.toml")
            info.type = kind
            info.linkname = "/etc/passwd"
            archive.addfile(info)
        dest = tmp_path / str(kind)
        dest.mkdir()

        with pytest.raises(ArchiveError) as caught:
            extract_archive(buffer.getvalue(), dest, LIMITS)

        assert caught.value.code == "unsafe_archive_member"
        assert list(dest.iterdir()) == []


def test_extracted_bytes_are_counted_not_the_declared_sizes(tmp_path):
    # 2 MB of zeros: the limit trips while streaming, before the member is written out.
    data = bytearray(zip_bytes({"big": bytes(2 << 20)}))
    limits = ArchiveLimits(max_members=5, max_extracted_bytes=1 << 20, max_compression_ratio=1e9)

    with pytest.raises(ArchiveError) as caught:
        extract_archive(bytes(data), tmp_path, limits)

    assert caught.value.code == "archive_too_large"


def test_a_deleted_character_s_running_job_is_cancelled_for_good(tmp_path, rig):
    store = RigStore(tmp_path / "rigs")
    store.open()
    try:
        store.jobs.write("ava", {"id": "ava", "job": "j1", "state": "running", "updated": 0.0})
        store.delete("ava")  # no rig yet: the job's record alone makes it a character
        late = store.jobs.update("ava", "j1", {"state": "done"})
        stored = store.put_job_result("ava", "j1", rig, b"character")
        record = store.jobs.read("ava")
    finally:
        store.close()

    assert record["state"] == "cancelled" and record["error"]["code"] == "character_deleted"
    assert not late and stored is None
    assert not store.exists("ava")
