"""The archive of TRC runs behind `import-trc --profile`: which run is the reference, each run
kept once, profiles read back as written."""

from __future__ import annotations

from contextlib import closing

import numpy as np

from services.tools.trc_import import ProfileArchive
from track.trc_profile import GridProfile

T0 = 1_772_000_000.0
DAY_S = 86_400.0


def grid(first_index: int, n: int, seed: int) -> GridProfile:
    rng = np.random.default_rng(seed)
    return GridProfile(first_index, 0.25, {"level_left_mm": rng.normal(size=n),
                                           "align_right_mm": rng.normal(size=n)})  # fmt: skip


def test_the_reference_is_the_latest_earlier_run_over_the_same_stretch(tmp_path):
    archive = ProfileArchive(tmp_path / "var" / "trc.sqlite")
    try:
        km0_2 = grid(0, 8001, 1)  # 0-2000 m
        assert archive.add("L1", "a", T0, km0_2)
        assert archive.add("L1", "c", T0 + 20 * DAY_S, grid(0, 8001, 3))
        assert archive.add("L1", "b", T0 + 10 * DAY_S, grid(0, 8001, 2))  # order of import
        assert archive.add("L1", "far", T0 + 30 * DAY_S, grid(40_000, 8001, 4))  # 10-12 km
        assert archive.add("L2", "other", T0 + 15 * DAY_S, grid(0, 8001, 5))
        assert archive.latest_before("L1", T0) is None
        assert archive.latest_before("L1", T0 + 15 * DAY_S).run_id == "b"
        assert archive.latest_before("L1", T0 + 40 * DAY_S, (500.0, 1800.0)).run_id == "c"
        assert archive.latest_before("L1", T0 + 40 * DAY_S, (1700.0, 3000.0)) is None  # 300 m
        assert archive.latest_before("L1", T0 + 40 * DAY_S).run_id == "far"
        back = archive.latest_before("L1", T0 + 5 * DAY_S).profile
        assert back.first_index == 0 and back.spacing_m == 0.25
        for name, values in km0_2.channels.items():
            assert np.array_equal(back.channels[name], values)
    finally:
        archive.close()


def test_a_run_imported_again_is_kept_once(tmp_path):
    path = tmp_path / "trc.sqlite"
    archive = ProfileArchive(path)
    try:
        assert archive.add("L1", "a", T0, grid(0, 100, 1))
        assert not archive.add("L1", "a", T0, grid(0, 100, 1))
        assert archive.add("L1", "a", T0 + DAY_S, grid(0, 100, 1))  # another run, same id
        assert archive.count("L1") == 2
    finally:
        archive.close()
    with closing(ProfileArchive(path)) as reopened:
        assert reopened.count("L1") == 2


def test_the_report_says_what_the_records_measure_and_what_they_cannot():
    from services.tools.trc_import import indicator_lines
    from track.trc_profile import PROFILE_COLUMNS, TrcProfile

    x = np.arange(0.0, 10.0, 0.25)

    def profile(*names: str) -> TrcProfile:
        return TrcProfile(x, {name: np.zeros_like(x) for name in names}, False)

    assert indicator_lines(profile(*PROFILE_COLUMNS)) == []  # both indicators, both rails
    assert indicator_lines(profile("level_right_mm")) == [
        "top6: from level_right_mm alone (the file has one rail of longitudinal level)",
        "align10: not measured, the file has no alignment column (align_left_mm, align_right_mm)",
    ]
