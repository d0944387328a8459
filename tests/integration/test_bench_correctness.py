"""Smoke test of bench/correctness.py: the --quick run computes finite figures.

No performance or target assertions (the real figures come from the default run, see
docs/science.md); only that the machinery works end to end on the pure cores. An integration test:
it runs the simulator and every core over weeks of a world, as a process (tens of seconds).
"""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load_bench():
    """bench/ is not an installed package: load the module from its file."""
    spec = importlib.util.spec_from_file_location(
        "bench_correctness", ROOT / "bench/correctness.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_quick_run_computes_finite_figures():
    proc = subprocess.run(
        [sys.executable, "-m", "bench.correctness", "--quick", "--json"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    fig = json.loads(proc.stdout)

    for name in ("fused", "alone"):
        assert fig[f"n_eval_{name}"] > 100
        for c in fig[f"coverage_{name}"]:
            assert c is not None and 0.5 <= c <= 1.0
    rmse = fig["rmse"]
    assert rmse["n"] > 10 and rmse["same_times"]
    for key in ("fused", "alone"):
        assert all(x is not None and math.isfinite(x) and x > 0 for x in rmse[key])
    crossings = fig["crossings_fused"]
    assert crossings["n"] > 0, "the quick world's truth crosses no limit: nothing checked"
    assert crossings["n"] == len(crossings["detail"])
    assert crossings["n"] == sum(line["crossings"] for line in crossings["by_line"].values())
    assert crossings["preceded"] == sum(line["preceded"] for line in crossings["by_line"].values())
    assert 0 <= crossings["preceded"] <= crossings["n"]
    assert fig["n_states"]["fused"] > fig["n_states"]["alone"] > 0
    assert fig["calibration"]["version"] >= 2  # fitted on the campaign's pairs
    assert fig["counts"]["withheld_TrcRecord"] > 0  # the TRC cut-off is in effect
    assert fig["counts"]["MaintenanceEvent"] > 0


def test_table_without_horizon_or_crossings():
    """A run too short for the RMSE horizon still prints every row (no figure, no verdict)."""
    correctness = _load_bench()
    settings, _ = correctness.parse_args(["--quick", "--days", "45"])
    fig = correctness.run(settings)
    rows = correctness.checks(fig)
    assert len(rows) == 6
    assert all(isinstance(r[1], str) and r[1] for r in rows)
    assert fig["rmse"]["n"] == 0
    assert {r[3] for r in rows if r[0].startswith("RMSE")} == {None}
