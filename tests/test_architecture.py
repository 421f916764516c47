"""Import contracts between the packages (the layers of README's tree: features -> map ->
engine -> server, features -> map -> builder -> builder service; the client stands alone).

Two views of "imports", both transitive: the static graph of every import statement in the
source (function-level imports included, which a run of one code path would miss), and the
modules a fresh interpreter really loads (which sees what third-party packages pull in)."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOTS = {"sfmloc": REPO / "service" / "sfmloc", "sfmloc_client": REPO / "client" / "sfmloc_client"}
TRANSPORTS = ("zenoh", "grpc")
# The client's contract modules (errors and their status table, camera models, names and keys,
# rotations), shared by client, server and builder: the only client code the core may load.
CLIENT_CONTRACT = (
    "sfmloc_client",
    "sfmloc_client.errors",
    "sfmloc_client.enums",
    "sfmloc_client.cameras",
    "sfmloc_client.keys",
    "sfmloc_client.rotations",
)

# (importer, forbidden, why): every module under `importer` never reaches any under `forbidden`.
CONTRACTS = [
    ("sfmloc.features", "sfmloc.server", "the per-frame core does not know who calls it"),
    ("sfmloc.engine", "sfmloc.server", "the per-frame core does not know who calls it"),
    ("sfmloc.engine", "sfmloc.builder", "the online engine reads maps, it does not build them"),
    ("sfmloc.engine", "sfmloc.builder_service", "the online engine does not build maps"),
    ("sfmloc.map", "sfmloc.engine", "the map format is read by the engine, not built on it"),
    ("sfmloc.map", "sfmloc.builder", "the map format is apart from its builder"),
    ("sfmloc.map", "sfmloc.server", "the map format is apart from its readers"),
    ("sfmloc.builder", "sfmloc.server", "the offline builder runs without the server"),
    ("sfmloc.builder", "sfmloc.engine", "the offline builder does not localize"),
    ("sfmloc.builder_service", "sfmloc.server", "the two services share the contract, not code"),
    (
        "sfmloc.server",
        "sfmloc.builder",
        "the server reads maps (sfmloc.map), it does not build them",
    ),
    ("sfmloc.server", "sfmloc.builder_service", "the two services share the contract, not code"),
    ("sfmloc_client", "sfmloc", "the client installs without the service"),
    ("sfmloc.viewer", "sfmloc.engine", "the viewer shows poses, it does not compute them"),
    ("sfmloc.viewer", "sfmloc.server", "the viewer listens to the pose stream like a client"),
    ("sfmloc.viewer", "sfmloc.builder", "the viewer reads bundles, it does not build them"),
]


def _module_name(path: Path) -> tuple[str, bool]:
    for top, root in ROOTS.items():
        if root in path.parents:
            parts = [top, *path.relative_to(root).with_suffix("").parts]
            if parts[-1] == "__init__":
                return ".".join(parts[:-1]), True
            return ".".join(parts), False
    raise AssertionError(path)


@cache
def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for root in ROOTS.values():
        for path in root.rglob("*.py"):
            name, is_pkg = _module_name(path)
            out[name] = (path, is_pkg)
    return out


def _resolve(name: str) -> str | None:
    """The module a dotted import name lands in (`a.b.Class` -> `a.b`); None if not ours."""
    mods = _modules()
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def _with_parents(name: str) -> set[str]:
    """Importing a.b.c runs a/__init__ and a/b/__init__ first."""
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts) + 1)}


@cache
def _direct_imports(name: str) -> tuple[frozenset[str], frozenset[str]]:
    """(our modules, third-party top-level packages) named by any import statement in `name`."""
    path, is_pkg = _modules()[name]
    package = name if is_pkg else name.rpartition(".")[0]
    ours: set[str] = set()
    others: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [module] + [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            if t.split(".")[0] in ROOTS:
                resolved = _resolve(t)
                if resolved:
                    ours |= _with_parents(resolved)
            else:
                others.add(t.split(".")[0])
    ours.discard(name)
    return frozenset(ours), frozenset(others)


def _reach(start: str) -> tuple[dict[str, str], set[str]]:
    """Every module of ours reachable from the modules under `start` (each with the module that
    first imported it, to print a chain), and the third-party packages they name."""
    seen: dict[str, str] = {}
    third: set[str] = set()
    todo = [m for m in _modules() if m == start or m.startswith(start + ".")]
    for m in todo:
        seen[m] = ""
    while todo:
        m = todo.pop()
        ours, others = _direct_imports(m)
        third |= others
        for n in ours:
            if n not in seen:
                seen[n] = m
                todo.append(n)
    return seen, third


def _chain(seen: dict[str, str], name: str) -> str:
    out = [name]
    while seen.get(out[-1]):
        out.append(seen[out[-1]])
    return " <- ".join(out)


def _under(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def test_the_graph_sees_the_imports_it_checks():
    """The scanner is not vacuous: it finds edges we know exist, lazy imports included."""
    assert "sfmloc.map.bundle" in _direct_imports("sfmloc.engine.matching")[0]
    assert "grpc" in _direct_imports("sfmloc_client.grpc_client")[1]
    seen, third = _reach("sfmloc.server")
    assert "sfmloc.engine.localizer" in seen and "zenoh" in third
    # build_jobs' child imports the builder inside a function: a static scan sees it
    assert "sfmloc.builder.build" in _reach("sfmloc.builder_service.jobs")[0]


@pytest.mark.parametrize(
    "importer,forbidden,why", CONTRACTS, ids=[f"{a}-not-{b}" for a, b, _ in CONTRACTS]
)
def test_import_contract(importer, forbidden, why):
    assert importer in _modules() and forbidden in _modules()
    seen, _ = _reach(importer)
    bad = sorted(m for m in seen if _under(m, forbidden))
    assert not bad, f"{importer} must not import {forbidden} ({why}): " + "; ".join(
        _chain(seen, m) for m in bad[:3]
    )


@pytest.mark.parametrize("core", ["sfmloc.features", "sfmloc.engine"])
def test_the_per_frame_core_names_no_transport(core):
    """No import statement reachable from the core names zenoh or grpc (nor the generated
    gRPC code, nor the client beyond its contract modules)."""
    seen, third = _reach(core)
    assert not third & set(TRANSPORTS), (core, sorted(third & set(TRANSPORTS)))
    client = [m for m in seen if _under(m, "sfmloc_client") and m not in CLIENT_CONTRACT]
    assert not client, [_chain(seen, m) for m in client]


# What a fresh interpreter loads: every module of each package imported, then sys.modules.
_PROBE = """
import importlib, json, pkgutil, sys
for pkg in sys.argv[1:]:
    mod = importlib.import_module(pkg)
    for info in pkgutil.walk_packages(mod.__path__, pkg + "."):
        importlib.import_module(info.name)
print(json.dumps(sorted(sys.modules)))
"""


def _loaded(*packages: str) -> list[str]:
    env_path = f"{ROOTS['sfmloc'].parent}:{ROOTS['sfmloc_client'].parent}"
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, *packages],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": env_path},
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_loading_the_per_frame_core_loads_no_transport():
    loaded = _loaded("sfmloc.features", "sfmloc.engine")
    assert "sfmloc.engine.localizer" in loaded  # the probe did import the core
    found = [
        m
        for m in loaded
        if m.split(".")[0] in TRANSPORTS
        or (_under(m, "sfmloc_client") and m not in CLIENT_CONTRACT)
    ]
    assert not found, found
    assert not [m for m in loaded if _under(m, "sfmloc.builder") or _under(m, "sfmloc.server")]


def test_loading_the_map_format_loads_neither_engine_nor_builder():
    loaded = _loaded("sfmloc.map")
    assert "sfmloc.map.bundle" in loaded
    assert not [m for m in loaded if m.split(".")[0] in TRANSPORTS]
    for pkg in ("sfmloc.engine", "sfmloc.builder", "sfmloc.server"):
        assert not [m for m in loaded if _under(m, pkg)], pkg


def test_loading_the_client_loads_no_service_code():
    loaded = _loaded("sfmloc_client")
    assert "sfmloc_client.grpc_client" in loaded
    assert not [m for m in loaded if _under(m, "sfmloc")]
