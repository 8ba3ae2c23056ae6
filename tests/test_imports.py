"""The facecast packages import each other without cycles, and only at module level.

The import graph is read from the source (AST), not by importing: an edge is an import at
module level. Two graphs: the run-time one (``if TYPE_CHECKING:`` blocks excluded, they run
only under a type checker) and the design one, which counts them too: a cycle hidden behind
``TYPE_CHECKING`` is still two modules that cannot be understood one without the other.
An import inside a function is allowed only where ``LAZY`` or ``CYCLE_DEBT`` below gives its
reason; one that dodges a cycle is the design saying a module holds two concepts.
"""

from __future__ import annotations

import ast
import fnmatch
import graphlib
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

_STARTUP_CLI = (
    "start-up time: `facecast` loads only the command it runs, and a command imports "
    "numpy, the rig engine (~0.7 s), the server or websockets when it runs"
)
_MATPLOTLIB = "start-up time: matplotlib (~0.5 s) loads only when a figure is drawn"

#: (importing module, imported module) patterns (fnmatch) -> why the import is deferred.
LAZY: dict[tuple[str, str], str] = {
    ("facecast.cli.main", "facecast.*.errors"): _STARTUP_CLI,
    ("facecast.cli.commands.*", "*"): _STARTUP_CLI,
    ("facecast.cli.bench.transport_client", "facecast.rig*"): (
        "start-up time of a client process (its wall time divides the servers' CPU): the rig "
        "engine (~1.3 s) loads only for the blend floor"
    ),
    ("facecast.cli.bench.servers", "facecast.server.*"): (
        "the server loads only in the subprocess that serves it: the benchmark starting it "
        "measures from outside"
    ),
    ("facecast.cli.snapshot", "*"): (
        "start-up time: the snapshot tool starts a server and Chromium (playwright) only "
        "when a command asks for a picture"
    ),
    ("facecast.client.fetch", "facecast.rig"): _STARTUP_CLI,
    ("facecast.cli.report", "matplotlib.*"): _MATPLOTLIB,
    ("facecast.cli.report", "facecast.cli.render"): _MATPLOTLIB,
    ("facecast.cli.render", "matplotlib.*"): _MATPLOTLIB,
    ("facecast.cli.loadgen", "matplotlib.*"): _MATPLOTLIB,
    ("facecast.cli.track", "playwright.*"): (
        "optional dependency: Playwright (the `test` extra) drives Chromium for `facecast "
        "track` only; without it the command says what to install"
    ),
    ("facecast.cli.bench.live", "playwright.*"): (
        "optional dependency: Playwright (the `test` extra) drives Chromium for `facecast bench "
        "live` only; the other benchmarks run without it"
    ),
    ("facecast.cli.facetrack", "cv2"): "optional dependency: the `perform` extra",
    ("facecast.cli.facetrack", "mediapipe.*"): "optional dependency: the `perform` extra",
    ("facecast.cli.eyelids", "mediapipe"): "optional dependency: the `perform` extra",
    ("facecast.cli.eyelids", "ai_edge_litert.*"): "optional dependency: the `perform` extra",
    ("facecast.server.channels.bus", "redis.asyncio"): (
        "start-up time: redis.asyncio (~0.2 s) only for a server given a Redis URL"
    ),
    ("facecast.server.serving.ws_guard", "uvicorn.protocols.websockets.websockets_impl"): (
        "chosen at run time: importing uvicorn's legacy implementation warns it is deprecated"
    ),
    ("facecast.server.pages.viewer", "facecast.rig.demo"): (
        "start-up time: the demo performance is generated only when /viewer asks for it"
    ),
}

#: Function-local imports that dodge a cycle today; each names the step that removes it.
#: The test fails when one of them is gone, so that this list shrinks with the code.
CYCLE_DEBT: dict[tuple[str, str], str] = {}

#: Import cycles that exist only through ``if TYPE_CHECKING:`` imports today (each the set
#: of modules of one strongly connected component), and the step that removes each. The
#: test fails on any other cycle, and when one of these is gone, so that this list shrinks.
TYPE_ONLY_CYCLE_DEBT: dict[frozenset[str], str] = {}


@dataclass(frozen=True)
class LocalImport:
    module: str
    target: str
    line: int


def _project_modules() -> dict[str, Path]:
    """Every facecast module, by dotted name, from pyproject's package list."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    modules = {}
    for package in config["packages"]:
        folder = ROOT / config["package-dir"][package]
        for path in sorted(folder.glob("*.py")):
            name = package if path.stem == "__init__" else f"{package}.{path.stem}"
            modules[name] = path
    return modules


def _extension_modules() -> set[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return {ext["name"] for ext in config.get("ext-modules", [])}


def _absolute(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    parts = module.split(".")
    if not is_package:
        parts = parts[:-1]
    if node.level > 1:
        parts = parts[: -(node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


def _targets(module: str, is_package: bool, node: ast.Import | ast.ImportFrom, known) -> list:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = _absolute(module, is_package, node)
    # ``from pkg import name`` imports the submodule pkg.name when there is one.
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]


def _is_type_checking(node: ast.If) -> bool:
    return "TYPE_CHECKING" in ast.unparse(node.test)


def _walk(module: str, path: Path, known: set[str]):
    """(run-time module-level edges, type-only edges, function-local imports) of one module."""
    is_package = path.stem == "__init__"
    edges: set[str] = set()
    type_only: set[str] = set()
    local: list[LocalImport] = []

    def visit(node: ast.AST, in_function: bool, typing: bool) -> None:
        for child in ast.iter_child_nodes(node):
            in_typing = typing or (
                isinstance(child, ast.If) and not in_function and _is_type_checking(child)
            )
            if isinstance(child, ast.Import | ast.ImportFrom):
                for target in _targets(module, is_package, child, known):
                    if in_function:
                        local.append(LocalImport(module, target, child.lineno))
                    elif target in known:
                        (type_only if in_typing else edges).add(target)
            function = isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            visit(child, in_function or function, in_typing)

    visit(ast.parse(path.read_text(), filename=str(path)), False, False)
    return edges, type_only - edges, local


@pytest.fixture(scope="module")
def graphs():
    """(run-time edges, edges counting type-only imports, function-local imports)."""
    modules = _project_modules()
    known = set(modules) | _extension_modules()
    edges, design, local = {}, {}, []
    for name, path in modules.items():
        edges[name], type_only, found = _walk(name, path, known)
        design[name] = edges[name] | type_only
        local.extend(found)
    return edges, design, local


@pytest.fixture(scope="module")
def graph(graphs):
    edges, _, local = graphs
    return edges, local


def _cycles(edges: dict[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            for target in successors:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(edges.get(target, ())))))
                    break
                if target in on_stack:
                    low[node] = min(low[node], index[target])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1 or node in edges.get(node, ()):
                        found.append(frozenset(component))
    return found


def _describe(component: frozenset[str], edges: dict[str, set[str]]) -> str:
    inner = sorted(
        f"{module} -> {target}"
        for module in component
        for target in edges.get(module, ())
        if target in component
    )
    return "{" + ", ".join(sorted(component)) + "}: " + "; ".join(inner)


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _reason(item: LocalImport, table: dict[tuple[str, str], str]) -> str | None:
    for (module, target), reason in table.items():
        if fnmatch.fnmatchcase(item.module, module) and fnmatch.fnmatchcase(item.target, target):
            return reason
    return None


def test_the_graph_sees_every_package_and_its_edges(graph):
    edges, _ = graph
    # Guards the reader itself: a walker that found no modules or no edges proves nothing.
    packages = {"facecast.protocol", "facecast.rig", "facecast.server", "facecast.client"}
    assert packages | {"facecast.cli"} <= set(edges)
    assert "facecast.rig.rig" in edges["facecast.rig.fit"]
    assert "facecast.rig.io.rigformat" in edges["facecast.rig.rig"]
    assert "facecast.rig._kernel" in edges["facecast.rig.kernel"]


def test_no_import_cycle_between_facecast_modules(graph):
    edges, _ = graph
    try:
        graphlib.TopologicalSorter(edges).prepare()
    except graphlib.CycleError as exc:
        pytest.fail("import cycle: " + " -> ".join(exc.args[1]))


def test_the_cycle_finder_finds_a_cycle_and_only_it():
    # Guards the finder itself: a finder that reports nothing proves nothing.
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert set(_cycles(edges)) == {frozenset("abc"), frozenset("e")}


def test_no_import_cycle_counting_type_only_imports(graphs):
    _, design, _ = graphs
    found = set(_cycles(design))
    new = [_describe(c, design) for c in found if c not in TYPE_ONLY_CYCLE_DEBT]
    assert not new, "import cycles (type-only imports included):\n" + "\n".join(new)
    paid = set(TYPE_ONLY_CYCLE_DEBT) - found
    assert not paid, f"paid off, remove from TYPE_ONLY_CYCLE_DEBT: {paid}"


#: The server's rooms, lowest first: a module imports only from its own room or a lower one
#: (server/SERVER.md, "Modules"). Rooms on one rank do not import each other; the base
#: modules at the top level (names, errors, settings, logs, daemon_pool) are one room.
SERVER_BASE = frozenset({"names", "errors", "settings", "logs", "daemon_pool", "heap"})
SERVER_ROOMS: tuple[tuple[str, ...], ...] = (
    ("base",),
    ("compute",),
    ("metrics",),
    ("storage", "serving"),
    ("guards",),
    ("connection",),
    ("stream", "channels", "http", "pages"),
    ("app",),
    ("runner",),
    ("testing",),
)


def _room(module: str) -> str | None:
    parts = module.split(".")
    if parts[:2] != ["facecast", "server"] or len(parts) < 3:
        return None
    return "base" if parts[2] in SERVER_BASE else parts[2]


def test_server_rooms_import_one_way(graphs):
    # Type-only imports count: a room that names a higher room's class in its annotations
    # cannot be read without it.
    _, edges, _ = graphs
    rank = {room: i for i, rooms in enumerate(SERVER_ROOMS) for room in rooms}
    rooms_seen = {_room(m) for m in edges if _room(m)}
    assert rooms_seen == set(rank), "a server module outside SERVER_ROOMS, or a room gone"
    upward = [
        f"{module} -> {target}"
        for module, targets in edges.items()
        if (room := _room(module))
        for target in targets
        if (other := _room(target)) and other != room and rank[other] >= rank[room]
    ]
    assert upward == []


def _rig_folder(module: str) -> str | None:
    """The room of ``rig/`` a module lives in: its subfolder, else its own top-level file."""
    parts = module.split(".")
    if parts[:2] != ["facecast", "rig"] or len(parts) < 3:
        return None
    return parts[2]


def test_rig_folders_import_each_other_without_a_cycle(graphs):
    # Folder level (rig/io, rig/characters, rig/sources, ..., each top-level module its own
    # room), type-only imports counted: two rooms that import each other are one concept
    # split in two places, whichever modules carry the arrows.
    _, edges, _ = graphs
    rooms: dict[str, set[str]] = {}
    for module, targets in edges.items():
        if (room := _rig_folder(module)) is None:
            continue
        rooms.setdefault(room, set()).update(
            other for t in targets if (other := _rig_folder(t)) not in (None, room)
        )
    assert {"io", "characters", "sources", "transfer", "evaluation"} <= set(rooms)
    assert _cycles(rooms) == []


def test_rig_imports_nothing_of_protocol_server_or_client(graph):
    edges, local = graph
    outside = ("facecast.protocol", "facecast.server", "facecast.client", "facecast.cli")
    found = [
        (module, target)
        for module, targets in edges.items()
        if module.startswith("facecast.rig")
        for target in targets
        if target.startswith(outside)
    ]
    found += [
        (i.module, i.target)
        for i in local
        if i.module.startswith("facecast.rig") and i.target.startswith(outside)
    ]
    assert not found


def test_the_client_library_and_the_server_import_nothing_of_the_cli(graph):
    # facecast.cli is built on the library; the library (and the server) never reach back.
    edges, local = graph
    found = [
        (module, target)
        for module, targets in edges.items()
        if module.startswith(("facecast.client", "facecast.server"))
        for target in targets
        if _within(target, "facecast.cli")
    ]
    found += [
        (i.module, i.target)
        for i in local
        if i.module.startswith(("facecast.client", "facecast.server"))
        and _within(i.target, "facecast.cli")
    ]
    assert not found


def test_every_function_local_import_has_a_reason(graph):
    _, local = graph
    unexplained = [
        f"{i.module}:{i.line} imports {i.target}"
        for i in local
        if _reason(i, LAZY) is None and _reason(i, CYCLE_DEBT) is None
    ]
    assert not unexplained, (
        "function-local imports without a reason (import at module level, or add the "
        "reason to LAZY in tests/test_imports.py):\n" + "\n".join(unexplained)
    )


def test_the_rig_engine_has_no_function_local_import_of_its_own(graph):
    _, local = graph
    assert not [i for i in local if i.module.startswith("facecast.rig")]


def test_every_cycle_debt_entry_is_still_owed(graph):
    _, local = graph
    owed = {key for key in CYCLE_DEBT if any(_reason(i, {key: ""}) is not None for i in local)}
    assert owed == set(CYCLE_DEBT), f"paid off, remove from CYCLE_DEBT: {set(CYCLE_DEBT) - owed}"
