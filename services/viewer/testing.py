"""Test helpers of the viewer: a planner's MaintenancePlan, and a recording read back with
the wheel's ``rerun`` CLI.

``rerun rrd verify`` checks that a file loads; ``rerun rrd print`` lists its chunks as
``Chunk(…) with N rows (…) - /entity/path - data columns: [Archetype:component …]``,
which :func:`rrd_contents` turns into rows per entity and component (the Python reader,
``rerun.chunk.RrdReader``, needs the ``rerun-sdk[catalog]`` extra; the CLI does not).
"""

from __future__ import annotations

import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

from schemas import MaintenancePlan, PlannedTamping

RERUN = Path(sys.executable).parent / "rerun"  # the venv's CLI, matching the SDK
_CHUNK = re.compile(r"^Chunk\(\S+\) with (\d+) rows .* - (/\S*) - data columns: \[(.*)\]$")


def rerun_cli(*args: str | Path, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    """Run the venv's ``rerun`` with ``args``."""
    return subprocess.run(
        [str(RERUN), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def verify_rrd(path: Path) -> None:
    """AssertionError with the CLI's output unless ``rerun rrd verify`` passes."""
    result = rerun_cli("rrd", "verify", path)
    assert result.returncode == 0, f"rerun rrd verify {path}:\n{result.stdout}\n{result.stderr}"


def rrd_contents(path: Path) -> dict[str, dict[str, int]]:
    """``{entity path: {"Archetype:component": rows}}`` of a recording (blueprint included)."""
    result = rerun_cli("rrd", "print", path)
    assert result.returncode == 0, f"rerun rrd print {path}:\n{result.stderr}"
    contents: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for line in result.stdout.splitlines():
        match = _CHUNK.match(line.strip())
        if match:
            rows, entity, columns = int(match[1]), match[2], match[3].split()
            for column in columns:
                contents[entity.removeprefix("/")][column] += rows
    return {entity: dict(columns) for entity, columns in contents.items()}


_VIEW_ROW = re.compile(r"┆ \[(2D|3D|[A-Za-z]\w*)\]\s+┆ \[([^\]]*)\]\s+┆ \[([^\]]*)\]\s+│")


def blueprint_views(path: Path) -> set[tuple[str, str]]:
    """``{(view class, space origin)}`` of every blueprint view in a recording, from the
    ``ViewBlueprint`` rows (class, display name, origin) that ``rrd print -vvv`` tabulates."""
    result = rerun_cli("rrd", "print", "-vvv", path)
    assert result.returncode == 0, f"rerun rrd print -vvv {path}:\n{result.stderr}"
    return {(m[1], m[3]) for m in _VIEW_ROW.finditer(result.stdout)}


def rrd_printout(path: Path) -> str:
    """``rerun rrd print -vvv`` of a recording: every chunk's cells (long texts cut after
    their first lines)."""
    result = rerun_cli("rrd", "print", "-vvv", path)
    assert result.returncode == 0, f"rerun rrd print -vvv {path}:\n{result.stderr}"
    return result.stdout


def make_plan(
    computed_at: float, rows: list[tuple[str, str, int, int]], week0_t: float
) -> MaintenancePlan:
    """A 26-week plan from ``week0_t`` with rows ``(line, segment, week, worksite)``, each
    200 m, its risk limit met."""
    return MaintenancePlan(
        t=week0_t, computed_at=computed_at, horizon_weeks=26, eps=0.05, status="optimal",
        objective=1.0, bound=1.0, gap=0.0, solve_s=0.1, km_per_week=[0.0] * 26,
        possessions=len({r[3] for r in rows if r[3] >= 0}), money=1.0, budget=None,
        segments=100, without_model=0,
        rows=[
            PlannedTamping(
                line=line, segment=segment, week=week, worksite=site, length_km=0.2,
                deadline_week=26, p_reach_ial=0.01, risk_met=True, cost=1.0, cost_untamped=2.0,
            )
            for line, segment, week, site in rows
        ],
    )  # fmt: skip
