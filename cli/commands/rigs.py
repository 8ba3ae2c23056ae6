"""``facecast rigs``: manage the rigs on a server through its REST API (/v1/rigs).

Talks HTTP only (httpx, imported when run); never imports facecast.server. Server errors
are shown with their stable ``code`` and exit status 2.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import urllib.parse
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from facecast.cli.errors import CommandError

if TYPE_CHECKING:
    from facecast.cli.commands import Subparsers

ARCHIVE_SUFFIXES = (".zip", ".tar", ".tar.gz", ".tgz")
#: A character file: sent to PUT /v1/characters/{id} (a .gltf zipped with its files).
CHARACTER_SUFFIXES = (".glb", ".vrm", ".gltf")


def register(subparsers: Subparsers) -> None:
    parser = subparsers.add_parser(
        "rigs",
        help="put, list, show, get and remove rigs on a server",
        description="Manage rigs on a facecast server (REST API under /v1/rigs). URL is the "
        "server's base URL, e.g. http://127.0.0.1:8000.",
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    def action(name: str, help: str, *names: str) -> argparse.ArgumentParser:
        command = sub.add_parser(name, help=help)
        command.add_argument("url", metavar="URL", help="server base URL")
        for arg in names:
            command.add_argument(arg, metavar=arg.upper())
        command.add_argument("--token", default=None, help="API token (default $FACECAST_TOKEN)")
        return command

    action("list", "list the rigs")
    action("show", "print a rig's summary as JSON", "name")
    put = action(
        "put",
        "store a rig: a character file (.glb, .vrm, or .gltf with its files; fitted on the "
        "server with the generic ARKit source set), an example-set folder or archive (fitted "
        "on the server), a rig file, or 'demo' (the built-in demo set, fitted here as "
        "'facecast fit demo' does)",
        "name",
        "path",
    )
    put.add_argument("--noise", type=float, default=None, help="fit: expected landmark noise")
    put.add_argument("--pca-threshold", type=float, default=None, help="fit: PCA threshold")
    put.add_argument("--kernel", default=None, help="fit: radial kernel")
    put.add_argument(
        "--clamp",
        choices=("nonneg", "unit"),
        default=None,
        help="fit: bound the non-neutral weights to >= 0 or [0, 1]",
    )
    put.add_argument(
        "--sparsity",
        type=float,
        default=None,
        metavar="S",
        help="fit, with --clamp: the sparsity prior (default 0, the plain projection)",
    )
    put.add_argument(
        "--rights-holder",
        action="store_true",
        help="a character file: you hold the rights to show it, so a VRM whose licence "
        "forbids redistribution is shown to viewers without a token too (default: only to "
        "viewers with one); kept with the character",
    )
    put.add_argument(
        "--expressions",
        choices=("transfer",),
        default=None,
        help="transfer: a character with only a neutral (or too few expressions) gets "
        "ICT-FaceKit's ARKit shapes by deformation transfer on the server first (a job; "
        "progress shown until it is live)",
    )
    put.add_argument(
        "--markers",
        metavar="FILE|auto",
        default=None,
        help="with --expressions transfer: correspondence markers ('source_vertex "
        "target_vertex' a line, sent as markers.txt beside the character in a zip), or auto; "
        "none for a face on ICT's own topology",
    )
    put.add_argument(
        "--names",
        nargs="+",
        metavar="NAME",
        default=None,
        help="with --expressions transfer: the ARKit names to make (default all it lacks)",
    )
    get = action("get", "save a rig's file (or with --glb its target mesh)", "name", "out")
    get.add_argument(
        "--glb", action="store_true", help="save the target mesh with morph targets instead"
    )
    action("rm", "remove a rig", "name")
    capture = action(
        "capture",
        "fit NAME@PERFORMER from a performer's captured expressions (a JSON capture file)",
        "name",
        "performer",
        "path",
    )
    capture.add_argument(
        "--noise", type=float, default=None, help="measured landmark spread (overrides the file's)"
    )
    refit = action("refit", "fit OTHER@PERFORMER from a performer's stored profile")
    refit.add_argument("--performer", required=True, metavar="NAME", help="the performer")
    refit.add_argument("--rig", required=True, metavar="OTHER", help="the character to refit onto")
    parser.set_defaults(func=run)


def _print_performer_fit(summary: dict[str, Any]) -> None:
    print(
        f"fitted {summary['id']}: M={summary['num_examples']} K={summary['num_points']} "
        f"(skipped: {', '.join(summary['skipped']) or 'none'})"
    )
    for message in summary.get("warnings", []):
        print(f"warning: {message}", file=sys.stderr)


def _zip_folder(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file() and not path.is_symlink():
                archive.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


def _gltf_archive(path: Path) -> bytes:
    """A zip of a .gltf and the files its buffers and images name (relative URIs inside its folder)."""
    return _zip_members(_gltf_members(path))


def _zip_members(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def _gltf_members(path: Path) -> dict[str, bytes]:
    """A .gltf and the files its buffers and images name, by path relative to its folder."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise CommandError(f"{path}: not a readable .gltf ({exc})") from None
    folder = path.parent.resolve()
    members = {path.name: path.read_bytes()}
    for kind in ("buffers", "images"):
        entries = doc.get(kind) if isinstance(doc, dict) else None
        for entry in entries if isinstance(entries, list) else []:
            uri = entry.get("uri") if isinstance(entry, dict) else None
            if not isinstance(uri, str) or uri.startswith("data:"):
                continue
            relative = urllib.parse.unquote(uri)
            target = (path.parent / relative).resolve()
            if "://" in uri or not target.is_relative_to(folder):
                raise CommandError(
                    f"{path}: {kind[:-1]} {uri!r} is outside the .gltf's folder; put its "
                    "files beside it (or export a .glb)"
                )
            if not target.is_file():
                raise CommandError(f"{path}: {kind[:-1]} {uri!r}: no such file beside it")
            members[target.relative_to(folder).as_posix()] = target.read_bytes()
    return members


def _transfer_body(path: Path, markers: str | None) -> bytes:
    """The character as sent for a transfer: as it is, or zipped with its markers.txt."""
    if markers is None or markers == "auto":
        return _gltf_archive(path) if path.suffix.lower() == ".gltf" else path.read_bytes()
    try:
        marker_bytes = Path(markers).read_bytes()
    except OSError as exc:
        raise CommandError(f"--markers {markers}: cannot read ({exc})") from None
    members = (
        _gltf_members(path) if path.suffix.lower() == ".gltf" else {path.name: path.read_bytes()}
    )
    members["markers.txt"] = marker_bytes
    return _zip_members(members)


def _follow_job(get_job: Any, job: dict[str, Any], *, interval: float = 0.5) -> dict[str, Any]:
    """Poll the job until it ends, a progress line on stderr; its final record."""
    import time

    while job["state"] not in ("done", "failed", "cancelled"):
        progress = job.get("progress") or {}
        stage = job.get("stage") or job["state"]
        print(
            f"\rtransferring: {progress.get('done', 0)}/{progress.get('total', '?')} "
            f"expressions ({stage})   ",
            end="",
            file=sys.stderr,
            flush=True,
        )
        time.sleep(interval)  # a REST resource to poll: nothing to wait on but time
        job = get_job()
    print(file=sys.stderr)
    return job


def _is_character(path: Path) -> bool:
    """A .glb/.vrm/.gltf by name, or any file that is a glTF binary by its first bytes."""
    if not path.is_file():
        return False
    if path.suffix.lower() in CHARACTER_SUFFIXES:
        return True
    with path.open("rb") as fh:
        return fh.read(4) == b"glTF"


def _print_character_fit(name: str, summary: dict[str, Any]) -> None:
    character = summary.get("character") or {}
    print(
        f"fitted {name} from a {character.get('format', 'glTF')} character: "
        f"M={summary['num_examples']} K={summary['num_points']} V={summary['num_vertices']}"
    )
    for line in summary.get("pairing", {}).get("text", []):
        print(line)
    if character.get("licence_note"):
        print(f"licence: {character['licence_note']}")
    for message in summary.get("warnings", []):
        print(f"warning: {message}", file=sys.stderr)


def _put_demo(args: argparse.Namespace, call: Any, rig_path: str) -> None:
    """``rigs put URL ID demo``: the built-in demo set fitted here, as ``facecast fit demo``
    fits it (with the fit options given), stored as a rig file."""
    from facecast.rig import fit
    from facecast.rig.demo import demo_example_set

    if args.expressions or args.markers or args.names or args.rights_holder:
        raise CommandError(
            "demo: --expressions, --markers, --names and --rights-holder are for a character "
            "file; the demo is an example set"
        )
    options: dict[str, Any] = {
        k: v
        for k, v in (
            ("noise", args.noise),
            ("pca_threshold", args.pca_threshold),
            ("clamp", args.clamp),
            ("sparsity", args.sparsity),
        )
        if v is not None
    }
    if args.kernel is not None:
        options["kernel"] = args.kernel
    rig = fit(demo_example_set(), **options)
    response = call("PUT", rig_path, content=rig.to_bytes())
    print(
        f"{'created' if response.status_code == 201 else 'replaced'} {args.name}: the demo "
        f"set fitted here, M={rig.num_examples} K={rig.num_points} V={rig.num_vertices}"
    )


def run(args: argparse.Namespace) -> int:
    import httpx

    base = args.url.rstrip("/")
    if not base.startswith(("http://", "https://")):
        raise CommandError(f"URL must start with http:// or https://, got {args.url!r}")
    token = args.token or os.environ.get("FACECAST_TOKEN")
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    def call(method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            with httpx.Client(base_url=base, headers=headers, timeout=600) as http:
                response = http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise CommandError(f"cannot reach {base}: {exc}") from None
        if response.status_code >= 400:
            try:
                problem = response.json()
                what = f"{problem.get('code', 'error')}: {problem.get('detail', '')}"
            except ValueError:
                what = response.text[:200]
            raise CommandError(f"{method} {path} -> {response.status_code} {what}")
        return response

    rig_path = f"/v1/rigs/{args.name}" if hasattr(args, "name") else ""
    if args.action == "list":
        rigs = call("GET", "/v1/rigs").json()["rigs"]
        for rig in rigs:
            print(f"{rig['id']}\t{rig['size']} bytes")
        if not rigs:
            print("(no rigs)", file=sys.stderr)
    elif args.action == "show":
        print(json.dumps(call("GET", rig_path).json(), indent=2))
    elif args.action == "put":
        path = Path(args.path)
        if args.path == "demo" and not path.exists():
            _put_demo(args, call, rig_path)
            return 0
        if not path.exists():
            raise CommandError(f"{path}: no such file or folder (or 'demo')")
        params = {
            k: v
            for k, v in (
                ("noise", args.noise),
                ("pca_threshold", args.pca_threshold),
                ("kernel", args.kernel),
                ("clamp", args.clamp),
                ("sparsity", args.sparsity),
            )
            if v is not None
        }
        if args.expressions is None and (args.markers or args.names):
            raise CommandError("--markers and --names go with --expressions transfer")
        if args.rights_holder:
            if not _is_character(path):
                raise CommandError(
                    f"{path}: --rights-holder is about a character file's licence "
                    "(.glb, .vrm, .gltf); a rig or an example set carries none"
                )
            params["rights_holder"] = "true"
        if args.expressions == "transfer":
            if not _is_character(path):
                raise CommandError(
                    f"{path}: --expressions transfer takes a character file (.glb, .vrm, .gltf)"
                )
            if args.markers == "auto":
                params["markers"] = "auto"
            if args.names:
                params["names"] = ",".join(args.names)
            params["expressions"] = "transfer"
            body = _transfer_body(path, args.markers)
            job = call("PUT", f"/v1/characters/{args.name}", content=body, params=params).json()
            print(
                f"transfer job for {args.name}: {len(job['expressions'])} expression(s) onto "
                f"{job['vertices']} vertices ({job['correspondence']} correspondence)"
            )
            job = _follow_job(lambda: call("GET", f"/v1/characters/{args.name}/job").json(), job)
            if job["state"] in ("failed", "cancelled"):
                error = job.get("error") or {}
                raise CommandError(
                    f"transfer {job['state']}: {error.get('code', 'error')}: "
                    f"{error.get('message', '')}"
                )
            result = job["result"]
            seconds = result["transfer"]["seconds"]
            print(
                f"transferred {len(result['transfer']['expressions'])} expression(s) in "
                f"{seconds['total']:.1f} s (correspondence {seconds['correspondence']:.1f} s, "
                f"solve {seconds['solve']:.1f} s), fitted in {seconds['fit']:.1f} s"
            )
            _print_character_fit(args.name, result)
        elif _is_character(path):
            body = _gltf_archive(path) if path.suffix.lower() == ".gltf" else path.read_bytes()
            summary = call("PUT", f"/v1/characters/{args.name}", content=body, params=params)
            _print_character_fit(args.name, summary.json())
        elif path.is_dir() or path.name.lower().endswith(ARCHIVE_SUFFIXES):
            body = _zip_folder(path) if path.is_dir() else path.read_bytes()
            summary = call("PUT", f"{rig_path}/examples", content=body, params=params).json()
            print(
                f"fitted {args.name}: M={summary['num_examples']} K={summary['num_points']} "
                f"V={summary['num_vertices']}"
                + (f", clamp {summary['clamp']}" if summary.get("clamp") else "")
            )
            for message in summary.get("warnings", []):
                print(f"warning: {message}", file=sys.stderr)
        else:
            if params:
                flags = ", ".join("--" + k.replace("_", "-") for k in params)
                raise CommandError(
                    f"{flags}: fit options apply to an example-set folder or archive, but "
                    f"{path} is a fitted rig file; refit it with facecast fit, or upload the "
                    "example set"
                )
            response = call("PUT", rig_path, content=path.read_bytes())
            print(f"{'created' if response.status_code == 201 else 'replaced'} {args.name}")
    elif args.action == "get":
        suffix = "model.glb" if args.glb else "rig"
        Path(args.out).write_bytes(call("GET", f"{rig_path}/{suffix}").content)
        print(f"wrote {args.out}")
    elif args.action == "rm":
        call("DELETE", rig_path)
        print(f"removed {args.name}")
    elif args.action == "capture":
        path = Path(args.path)
        try:
            body = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise CommandError(f"{path}: no such file") from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise CommandError(f"{path}: not a JSON capture ({exc})") from None
        if args.noise is not None and isinstance(body, dict):
            body["noise"] = args.noise
        _print_performer_fit(
            call("PUT", f"{rig_path}/performer/{args.performer}", json=body).json()
        )
    elif args.action == "refit":
        _print_performer_fit(
            call("POST", f"/v1/performers/{args.performer}/refit", params={"rig": args.rig}).json()
        )
    return 0
