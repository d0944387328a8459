"""The layering the architecture promises (docs/architecture.md), checked over the source.

From the bottom up:

- ``schemas`` (the wire contract) imports nothing of ours.
- ``track`` (the track register) imports only ``schemas``: it neither knows the services nor
  the simulators; whoever wants a packaged network passes its path.
- The shared layer of the services: ``services.runtime`` (the bus, delivery, inboxes and
  configuration every process uses), ``services.defaults`` (the packaged default files and how
  they are found and read), ``services.limits`` (the limits per line speed class that
  filtering, alerting and the planner apply) and ``services.drift_diffusion`` (the
  degradation model's posterior, which calibration fits and the frequency study draws from).
  It imports ``schemas``, ``track`` and itself, no service.
- A service (``services/<name>/`` of :data:`SERVICES`) imports the shared layer, ``schemas``,
  ``track`` and itself: no service imports another one, so each deploys and changes alone.
- The commands (``services/tools``, ``services/cli.py``) put the services together: they may
  import any of them, by public names only.
- No part of ``services`` imports the simulators, the benchmarks or the tests: a deployment
  without the simulator must run.
- The simulators publish like a gateway would: the runtime is infrastructure, not a service,
  and ``services.defaults`` is package data, not a service, so ``simulators`` may import those
  two (and ``schemas``, ``track``), no service.
- ``bench`` may import anything, by public names only.

And across all of them: no import cycle, counting the imports inside functions (an import
deferred to dodge a cycle is still one).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("schemas", "services", "simulators", "track", "bench")
OURS = (*PACKAGES, "tests")
SERVICES = ("alerting", "calibration", "extraction", "filtering", "ingestion", "planning", "viewer")
SHARED = ("services.runtime", "services.defaults", "services.limits", "services.drift_diffusion")
COMMANDS = ("services.tools", "services.cli")
# Layer of a module (the longest prefix that matches) -> the modules it may import.
ALLOWED: dict[str, tuple[str, ...]] = {
    "schemas": ("schemas",),
    "track": ("schemas", "track"),
    **{shared: ("schemas", "track", *SHARED) for shared in SHARED},
    **{f"services.{s}": ("schemas", "track", *SHARED, f"services.{s}") for s in SERVICES},
    **{command: ("schemas", "track", "services") for command in COMMANDS},
    "simulators": ("schemas", "track", "simulators", "services.runtime", "services.defaults"),
    "bench": OURS,  # the benchmarks drive a browser with the tests' helper (tests.browser)
    "services": (),  # the package itself (its __init__) imports nothing
}
# Where only public names of our modules may be used (imported or reached as attributes).
PUBLIC_ONLY = ("bench", *COMMANDS)


@dataclass(frozen=True)
class Import:
    path: Path
    line: int
    module: str  # the module of ours it loads
    names: tuple[str, ...]  # the names taken from it (``from module import names``)


def within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def module_of(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def source_files(root: Path, packages: Iterable[str] = PACKAGES) -> list[Path]:
    return sorted(p for package in packages for p in (root / package).rglob("*.py"))


def imports(path: Path, root: Path, modules: set[str]) -> Iterator[Import]:
    """Every import of one of ``modules`` in ``path``, at any depth (in functions too), with
    relative imports resolved; ``from package import submodule`` loads the submodule."""
    here = module_of(path, root)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in OURS:
                    yield Import(path, node.lineno, alias.name, ())
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            if module.split(".")[0] not in OURS:
                continue
            names = tuple(alias.name for alias in node.names)
            submodules = [n for n in names if f"{module}.{n}" in modules]
            for name in submodules:
                yield Import(path, node.lineno, f"{module}.{name}", ())
            rest = tuple(n for n in names if n not in submodules)
            if rest or not submodules:
                yield Import(path, node.lineno, module, rest)


def all_imports(root: Path, packages: Iterable[str] = PACKAGES) -> list[Import]:
    files = source_files(root, packages)
    modules = {module_of(p, root) for p in files}
    return [i for p in files for i in imports(p, root, modules)]


def layer(module: str) -> str | None:
    matches = [name for name in ALLOWED if within(module, name)]
    return max(matches, key=len) if matches else None


def layering_violations(root: Path) -> list[str]:
    wrong = []
    for imp in all_imports(root):
        importer = module_of(imp.path, root)
        name = layer(importer)
        if name is None:
            wrong.append(f"{imp.path.relative_to(root)}: in no layer of ALLOWED")
        elif not any(within(imp.module, allowed) for allowed in ALLOWED[name]):
            wrong.append(f"{imp.path.relative_to(root)}:{imp.line} imports {imp.module}")
    return wrong


def private_uses(root: Path) -> list[str]:
    """Private names of our modules taken in :data:`PUBLIC_ONLY`: ``from x import _y`` and
    ``anything._y`` (a single leading underscore), except on ``self``, ``cls`` and a module not
    of ours imported by name (``argparse._SubParsersAction``)."""
    files = source_files(root, [p.replace(".", "/") for p in PUBLIC_ONLY])
    files += [root / f"{p.replace('.', '/')}.py" for p in PUBLIC_ONLY]
    modules = {module_of(p, root) for p in source_files(root)}
    found = []
    for path in sorted(p for p in set(files) if p.is_file()):
        where = path.relative_to(root)
        for imp in imports(path, root, modules):
            if any(_private(part) for part in imp.module.split(".")):
                found.append(f"{where}:{imp.line} imports {imp.module}")
            found += [
                f"{where}:{imp.line} imports {imp.module}.{n}" for n in imp.names if _private(n)
            ]
        tree = ast.parse(path.read_text(), str(path))
        foreign = {"self", "cls", *_foreign_names(tree)}
        for node in ast.walk(tree):
            owner = getattr(node, "value", None)
            if (
                isinstance(node, ast.Attribute)
                and _private(node.attr)
                and not (isinstance(owner, ast.Name) and owner.id in foreign)
            ):
                found.append(f"{where}:{node.lineno} uses {ast.unparse(node)}")
    return found


def _foreign_names(tree: ast.Module) -> set[str]:
    """The names a file binds to modules not of ours (``import argparse``, ``from os import
    path``): their private names are the standard library's or a dependency's business."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom) and not getattr(node, "level", 0):
            modules = (
                [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module]
            )
            if all(m.split(".")[0] not in OURS for m in modules):
                names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def import_cycles(root: Path) -> list[list[str]]:
    """One cycle through every strongly connected group of the module import graph."""
    graph: dict[str, set[str]] = {module_of(p, root): set() for p in source_files(root)}
    for imp in all_imports(root):
        if imp.module in graph:
            graph[module_of(imp.path, root)].add(imp.module)
    cycles = []
    for group in _strongly_connected(graph):
        if len(group) > 1 or any(m in graph[m] for m in group):
            cycles.append(_cycle_in(sorted(group)[0], graph, group))
    return sorted(cycles)


def _strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm, iterative."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    group = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        group.add(member)
                        if member == node:
                            break
                    groups.append(group)
    return groups


def _cycle_in(start: str, graph: dict[str, set[str]], group: set[str]) -> list[str]:
    """A shortest path from ``start`` back to itself inside ``group`` (breadth first)."""
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for nxt in sorted(graph[node] & group):
                if nxt == start:
                    return [*paths[node], start]
                if nxt not in paths:
                    paths[nxt] = [*paths[node], nxt]
                    following.append(nxt)
        frontier = following
    raise AssertionError(f"{start} is in no cycle")


def test_every_file_is_in_a_layer() -> None:
    files = source_files(ROOT)
    assert len(files) > 50
    modules = [module_of(p, ROOT) for p in files]
    assert [m for m in modules if layer(m) in (None, "services") and m != "services"] == []


def test_a_layer_imports_only_what_it_may() -> None:
    assert layering_violations(ROOT) == []


def test_the_commands_and_benchmarks_use_public_names_only() -> None:
    assert private_uses(ROOT) == []


def test_no_import_cycle() -> None:
    cycles = import_cycles(ROOT)
    assert cycles == [], "\n".join(" -> ".join(cycle) for cycle in cycles)


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


@pytest.mark.parametrize(
    ("name", "text", "expected"),
    [
        (
            "track/a.py",
            "from services.defaults import x\n",
            "track/a.py:1 imports services.defaults",
        ),
        ("track/a.py", "def f():\n    import simulators.b\n", "track/a.py:2 imports simulators.b"),
        (
            "services/alerting/a.py",
            "from ..calibration import posterior\n",
            "services/alerting/a.py:1 imports services.calibration.posterior",
        ),
        (
            "services/limits.py",
            "from services import viewer\n",
            "services/limits.py:1 imports services.viewer",
        ),
        ("schemas/a.py", "from track.b import c\n", "schemas/a.py:1 imports track.b"),
        (
            "simulators/a.py",
            "import services.ingestion.b\n",
            "simulators/a.py:1 imports services.ingestion.b",
        ),
        (
            "services/tools/a.py",
            "from simulators import b\n",
            "services/tools/a.py:1 imports simulators.b",
        ),
    ],
)
def test_the_layering_check_sees_a_forbidden_import(
    tmp_path: Path, name: str, text: str, expected: str
) -> None:
    root = _tree(
        tmp_path,
        {
            name: text,
            "services/calibration/posterior.py": "",
            "services/viewer/__init__.py": "",
            "simulators/b.py": "",
            "services/defaults/__init__.py": "",
        },
    )
    assert layering_violations(root) == [expected]


def test_the_private_check_sees_private_names(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "bench/a.py": (
                "from services.runtime.inbox import _Inbox, Inbox\n"
                "import services.runtime._hidden\n"
                "import argparse\n"
                "class A(argparse._SubParsersAction):\n"
                "    def f(self, other):\n"
                "        return self._ok, other._state, Inbox.__name__\n"
            ),
            "services/tools/b.py": "from ..runtime import inbox\nx = inbox._take\n",
            "services/runtime/inbox.py": "",
            "services/runtime/_hidden.py": "",
        },
    )
    assert private_uses(root) == [
        "bench/a.py:1 imports services.runtime.inbox._Inbox",
        "bench/a.py:2 imports services.runtime._hidden",
        "bench/a.py:6 uses other._state",
        "services/tools/b.py:2 uses inbox._take",
    ]


def test_the_cycle_check_sees_a_cycle(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "track/a.py": "from track import b\n",
            "track/b.py": "def f():\n    from .c import g\n",
            "track/c.py": "import track.a\n",
            "track/d.py": "from track.a import x\n",
        },
    )
    assert import_cycles(root) == [["track.a", "track.b", "track.c", "track.a"]]


def test_the_sizes_stay_readable() -> None:
    """No production file over 800 lines, no function over 100: past that, a reader can no
    longer hold a module or a function in mind, and it mixes roles."""
    long = []
    for path in source_files(ROOT, ("schemas", "services", "track")):
        text = path.read_text()
        where = path.relative_to(ROOT)
        if (lines := len(text.splitlines())) > 800:
            long.append(f"{where}: {lines} lines")
        for node in ast.walk(ast.parse(text, str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = node.end_lineno - node.lineno + 1
                if length > 100:
                    long.append(f"{where}:{node.lineno} {node.name}: {length} lines")
    assert long == []
