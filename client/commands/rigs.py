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
import zipfile
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "rigs",
        help="list, upload, fit, download and delete rigs on a server",
        description="Manage rigs on a facecast server (REST API under /v1/rigs).",
    )
    parser.add_argument(
        "--server",
        default=None,
        help="server base URL (default $FACECAST_SERVER or http://127.0.0.1:8000)",
    )
    parser.add_argument("--token", default=None, help="API token (default $FACECAST_TOKEN)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    sub.add_parser("list", help="list rigs")
    show = sub.add_parser("show", help="print a rig's metadata as JSON")
    show.add_argument("id")

    upload = sub.add_parser("upload", help="store a fitted rig file under ID")
    upload.add_argument("id")
    upload.add_argument("file", type=Path, help="a rig file written by `facecast fit`")

    fit = sub.add_parser(
        "fit", help="upload an example-set folder or archive and fit it on the server"
    )
    fit.add_argument("id")
    fit.add_argument(
        "examples", type=Path, help="folder with facecast.toml, or a .zip/.tar/.tar.gz of one"
    )
    fit.add_argument("--noise", type=float, default=None)
    fit.add_argument("--pca-threshold", type=float, default=None)
    fit.add_argument("--kernel", default=None)

    download = sub.add_parser("download", help="save the rig file")
    download.add_argument("id")
    download.add_argument("out", type=Path)

    model = sub.add_parser("model", help="save the target mesh with morph targets (.glb)")
    model.add_argument("id")
    model.add_argument("out", type=Path)

    delete = sub.add_parser("delete", help="delete a rig")
    delete.add_argument("id")
    parser.set_defaults(func=run)


def _zip_folder(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file() and not path.is_symlink():
                archive.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


def run(args: argparse.Namespace) -> int:
    import httpx

    from facecast.client.cli import CommandError

    base = (args.server or os.environ.get("FACECAST_SERVER") or "http://127.0.0.1:8000").rstrip("/")
    token = args.token or os.environ.get("FACECAST_TOKEN")
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    def call(method: str, path: str, **kwargs) -> httpx.Response:
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

    rig_path = f"/v1/rigs/{args.id}" if hasattr(args, "id") else ""
    if args.action == "list":
        rigs = call("GET", "/v1/rigs").json()["rigs"]
        for rig in rigs:
            print(f"{rig['id']}\t{rig['size']} bytes")
        if not rigs:
            print("(no rigs)", file=sys.stderr)
    elif args.action == "show":
        print(json.dumps(call("GET", rig_path).json(), indent=2))
    elif args.action == "upload":
        response = call("PUT", rig_path, content=args.file.read_bytes())
        print(f"{'created' if response.status_code == 201 else 'replaced'} {args.id}")
    elif args.action == "fit":
        examples = args.examples
        body = _zip_folder(examples) if examples.is_dir() else examples.read_bytes()
        params = {
            k: v
            for k, v in (
                ("noise", args.noise),
                ("pca_threshold", args.pca_threshold),
                ("kernel", args.kernel),
            )
            if v is not None
        }
        response = call("PUT", f"{rig_path}/examples", content=body, params=params)
        summary = response.json()
        print(
            f"fitted {args.id}: M={summary['num_examples']} K={summary['num_points']} "
            f"V={summary['num_vertices']}"
        )
    elif args.action == "download":
        args.out.write_bytes(call("GET", f"{rig_path}/rig").content)
        print(f"wrote {args.out}")
    elif args.action == "model":
        args.out.write_bytes(call("GET", f"{rig_path}/model.glb").content)
        print(f"wrote {args.out}")
    elif args.action == "delete":
        call("DELETE", rig_path)
        print(f"deleted {args.id}")
    return 0
