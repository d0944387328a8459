"""Write the two example TRC profile exports of README.md, "TRC profiles", reproducibly.

Two runs of the Track Recording Car over 1.3 km of the demo network's line L1 (true
chainage 2950-4250 m), on the same track with fresh measurement noise (0.15 mm):

* ``trc-L1-run1.csv``: recorded ascending, positions right, with lat/lon;
* ``trc-L1-run2.csv``: recorded descending, its chainage 6 m short of the true one and
  drifting by a further 0.3 m over the run (the car's odometer), without lat/lon.

``python docs/examples/make_trc_profiles.py`` (from the repository root) rewrites them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.defaults import demo_network
from simulators.profile import LineProfile

HERE = Path(__file__).resolve().parent
SEED = 7
NOISE_MM = 0.15
CHANNELS = ("level_left_mm", "level_right_mm", "align_left_mm", "align_right_mm")


def main() -> None:
    line = demo_network().lines["L1"]
    bounds = np.stack([line.segment_starts_m, line.segment_ends_m], -1)
    track = LineProfile("L1", bounds, seed=SEED)
    rng = np.random.default_rng(SEED)
    n = len(bounds)
    z = np.stack([rng.normal(np.log(1.6), 0.4, n), rng.normal(np.log(1.3), 0.4, n)], -1)
    track.update(z, np.zeros(n, dtype=np.int64))
    true_m = np.arange(2950.0, 4250.0, 0.25)
    for name, recorded_m, descending, with_position in (
        ("trc-L1-run1.csv", true_m, False, True),
        ("trc-L1-run2.csv", true_m - 6.0 - 0.3 * (true_m - true_m[0]) / 1300.0, True, False),
    ):
        p = track.sample(true_m) + rng.normal(0.0, NOISE_MM, (4, true_m.size))
        columns = ["chainage_m", *CHANNELS]
        rows = [recorded_m, *p]
        formats = ["%.3f"] + ["%.2f"] * 4
        if with_position:
            lonlat = line.lonlat_at(true_m)
            columns += ["lat", "lon"]
            rows += [lonlat[:, 1], lonlat[:, 0]]
            formats += ["%.7f", "%.7f"]
        table = np.stack(rows, -1)
        if descending:
            table = table[::-1]
        header = (
            f"# TRC profile export, line L1, {'descending' if descending else 'ascending'}, "
            "0.25 m sampling (synthetic: docs/examples/make_trc_profiles.py)\n" + ",".join(columns)
        )
        np.savetxt(HERE / name, table, fmt=formats, delimiter=",", header=header, comments="")


if __name__ == "__main__":
    main()
