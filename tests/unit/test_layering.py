"""Which package may import which: the layering the architecture promises, over the source.

``schemas`` (the wire contract) imports nothing of ours; ``track`` (the track register)
only ``schemas`` and the packaged default files; the services never import the simulators
(nor the benchmarks or the tests): a deployment without the simulator must run.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
OURS = ("schemas", "services", "simulators", "track", "bench", "tests")
ALLOWED = {
    "schemas": {"schemas"},
    "track": {"schemas", "track", "services.defaults"},
    "services": {"schemas", "track", "services"},
}


def imported_modules(path: Path) -> set[str]:
    """Every absolute module name a file imports (``import a.b``, ``from a.b import c``)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


def allowed(module: str, prefixes: set[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_a_package_imports_only_the_layers_below_it(package: str) -> None:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no source under {package}/"
    wrong = [
        f"{path.relative_to(ROOT)} imports {module}"
        for path in files
        for module in sorted(imported_modules(path))
        if module.split(".")[0] in OURS and not allowed(module, ALLOWED[package])
    ]
    assert wrong == []


def test_the_check_sees_a_forbidden_import(tmp_path: Path) -> None:
    source = tmp_path / "bad.py"
    source.write_text("import numpy\nfrom simulators.network import stable_rng\n")
    found = {m for m in imported_modules(source) if m.split(".")[0] in OURS}
    assert found == {"simulators.network"}
    assert not allowed("simulators.network", ALLOWED["services"])
