"""Stack entries the end-to-end tests of `trackfusion up` share."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def estimation_on(network: str, state_dir: Path) -> list[dict[str, Any]]:
    """Stack entries of calibration and filtering on ``network`` (``{network}``: the stack's
    ``--network``), each with its store in ``state_dir``."""
    return [
        {"name": "calibration",
         "args": ["--db", str(state_dir / "cal.sqlite"), "--instance", "calibration",
                  "--initial-models", "{defaults}/initial-models.json5", "--network", network]},
        {"name": "filtering",
         "args": ["--db", str(state_dir / "f.sqlite"), "--instance", "filtering",
                  "--network", network]},
    ]  # fmt: skip
