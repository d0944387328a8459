"""`trackfusion import-trc` as a real process: good rows of a per-segment export arrive and
bad rows are reported; with ``--profile``, two runs of a line, the second aligned to the
first, their TrcRecords on the bus; the archive keeps each run once. With a filtering
service in a thread: the import is confirmed when filtering holds its records, also when
filtering starts while the import waits; without filtering it exits 3 naming the segments."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pytest
import zenoh
from support import run_cli

from schemas import TrcRecord, decode, encode, keys
from services.filtering import service
from services.filtering.testing import example_models
from services.tools.trc_import import EXIT_UNCONFIRMED, ProfileArchive

EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"
SEGMENTS = [f"s000{k}" for k in range(15, 21)]  # what the 1.3 km of the examples cover


@pytest.fixture
def published(open_session, namespace, collector) -> Iterator:
    """The TrcRecords published in the test's namespace, as they arrive."""
    received = collector(lambda sample: decode(sample.payload.to_bytes(), TrcRecord))
    subscriber = open_session().declare_subscriber(f"{namespace}/trc/**", received)
    yield received
    subscriber.undeclare()


def test_import_trc_publishes_good_rows_and_reports_bad_ones(
    published, router, namespace, tmp_path
):
    export = tmp_path / "trc.csv"
    export.write_text(
        "line,segment,t,top6_mm,align10_mm,run_id\n"
        "L1,s00001,2026-03-01T10:00:00Z,4.2,3.1,r1\n"
        "L1,s00002,2026-03-01T10:00:09Z,0,3.1,r1\n"
        "L1,s00003,2026-03-01T10:00:18Z,3.9,2.8,r1\n"
    )
    wiring = ("--connect", router, "--ns", namespace, "--no-wait")
    result = run_cli("import-trc", str(export), *wiring, timeout=60)
    assert result.returncode == 1, result.stderr  # bad rows were reported
    assert f"{export}:3: TrcRecord" not in result.stderr  # the reason is the message's own
    assert f"{export}:3:" in result.stderr and "top6_mm" in result.stderr
    assert "published 2 TRC records, 1 bad rows" in result.stdout
    got = sorted((published.get().segment, published.get().segment))
    assert got == ["s00001", "s00003"]
    missing = run_cli("import-trc", str(tmp_path / "nope.csv"), *wiring, timeout=60)
    assert missing.returncode != 0 and "cannot read" in missing.stderr


def test_two_runs_are_published_the_second_aligned_to_the_first(
    published, router, namespace, tmp_path
):
    archive = tmp_path / "trc-profiles.sqlite"
    wiring = ("--connect", router, "--ns", namespace, "--archive", str(archive), "--no-wait")

    def import_run(name: str, run_id: str, t: str):
        result = run_cli(
            "import-trc", "--profile", str(EXAMPLES / name), "--line", "L1",
            "--run-id", run_id, "--t", t, *wiring, timeout=60,
        )  # fmt: skip
        assert result.returncode == 0, result.stderr
        records = sorted((published.get() for _ in SEGMENTS), key=lambda r: r.segment)
        assert [r.segment for r in records] == SEGMENTS
        assert {(r.line, r.run_id) for r in records} == {("L1", run_id)}
        return result.stdout, records

    dry = run_cli(
        "import-trc", "--profile", str(EXAMPLES / "trc-L1-run1.csv"), "--line", "L1",
        "--run-id", "dry", "--t", "2026-03-01T09:00:00Z", "--dry-run", *wiring, timeout=60,
    )  # fmt: skip
    assert dry.returncode == 0, dry.stderr
    assert "dry run: nothing published, nothing archived" in dry.stdout
    assert not archive.exists()  # and its records, had it published any, come first below
    report, first = import_run("trc-L1-run1.csv", "r1", "2026-03-02T09:00:00Z")
    assert "no earlier run of this stretch of the line" in report
    assert "skipped, not fully covered by the run: 2 (s00014, s00021)" in report

    report, second = import_run("trc-L1-run2.csv", "r2", "2026-05-04T09:00:00Z")
    assert "descending" in report and "5 of 6 windows used" in report
    windows = [row.split() for row in report.splitlines() if row.startswith("  ")]
    offsets = [float(row[1]) for row in windows if row[3:] == ["used"]]
    assert len(offsets) == 5  # the example's odometer: 6 m, drifting by 0.3 m over the run
    assert all(6.0 < offset < 6.35 for offset in offsets), report
    for a, b in zip(first, second, strict=True):
        assert b.top6_mm == pytest.approx(a.top6_mm, abs=0.1)
        assert b.align10_mm == pytest.approx(a.align10_mm, abs=0.1)
    assert "profile archived in" in report

    report, again = import_run("trc-L1-run2.csv", "r2", "2026-05-04T09:00:00Z")
    assert "run already in the archive" in report
    assert [(r.top6_mm, r.align10_mm) for r in again] == [(r.top6_mm, r.align10_mm) for r in second]
    with closing(ProfileArchive(archive)) as store:
        assert store.count("L1") == 2


def test_a_bad_profile_is_refused_with_its_line_numbers_and_nothing_is_archived(
    router, namespace, tmp_path
):
    export = tmp_path / "run.csv"
    export.write_text(
        "# TRC export\nchainage_m,level_left_mm,align_left_mm\n"
        "0,1,2\n0.25,1,2\n0.75,1,2\n1.0,oops,2\n"
    )
    archive = tmp_path / "trc-profiles.sqlite"
    result = run_cli(
        "import-trc", "--profile", str(export), "--line", "L1", "--run-id", "r1",
        "--t", "2026-03-02T09:00:00Z", "--connect", router, "--ns", namespace,
        "--archive", str(archive), timeout=60,
    )  # fmt: skip
    assert result.returncode == 2
    assert f"{export}:6: level_left_mm: 'oops' is not a finite number" in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("trackfusion import-trc: --profile")
    assert not archive.exists()


EXPORT = (
    "line,segment,t,top6_mm,align10_mm,run_id\n"
    "L1,s00001,2026-03-01T10:00:00Z,4.2,3.1,r1\n"
    "L1,s00002,2026-03-01T10:00:09Z,3.9,2.8,r1\n"
)


@pytest.fixture
def start_filtering(open_session, service_config, tmp_path, service_thread):
    """``start_filtering()``: a filtering instance in a thread, with the example models
    answered on model/** (for calibration), ready when it returns."""
    models = [(keys.key_of(service_config.ns, m), encode(m)) for m in example_models(30, seed=0)]

    def on_query(query: zenoh.Query) -> None:
        for key, payload in models:
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                query.reply(key, payload)

    queryable = open_session().declare_queryable(keys.model_all(service_config.ns), on_query)

    def start():
        return service_thread(
            "filtering",
            lambda stop: service.main(
                service_config,
                db=tmp_path / "filtering.sqlite",
                stop=stop,
                handle_signals=False,
            ),
            alive=keys.alive(service_config.ns, service.SERVICE, "test"),
        )

    yield start
    queryable.undeclare()


def test_a_profile_import_is_confirmed_by_the_running_filtering(
    start_filtering, router, namespace, tmp_path
):
    start_filtering()
    result = run_cli(
        "import-trc", "--profile", str(EXAMPLES / "trc-L1-run1.csv"), "--line", "L1",
        "--run-id", "r1", "--t", "2026-03-02T09:00:00Z", "--connect", router, "--ns", namespace,
        "--archive", str(tmp_path / "trc-profiles.sqlite"), timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"confirmed {len(SEGMENTS)} of {len(SEGMENTS)} TRC records" in result.stdout


def test_an_import_is_put_again_until_filtering_starts_and_holds_it(
    start_filtering, spawn, router, namespace, tmp_path
):
    export = tmp_path / "trc.csv"
    export.write_text(EXPORT)
    wiring = ("--connect", router, "--ns", namespace)
    importing = spawn("import", "import-trc", str(export), *wiring, "--wait-s", "120")
    assert importing.line(60) == "published 2 TRC records, 0 bad rows"
    assert importing.line(60).startswith("waiting up to 120 s for filtering to confirm 2")
    start_filtering()  # after the records went out: it gets them from the command's puts
    assert importing.wait(120) == 0, importing.log()
    assert "confirmed 2 of 2 TRC records" in importing.stdout()


def test_an_import_no_filtering_holds_names_its_segments_and_fails(router, namespace, tmp_path):
    export = tmp_path / "trc.csv"
    export.write_text(EXPORT)
    result = run_cli(
        "import-trc", str(export), "--connect", router, "--ns", namespace, "--wait-s", "2",
        timeout=60,
    )  # fmt: skip
    assert result.returncode == EXIT_UNCONFIRMED, result.stderr
    assert "confirmed 0 of 2 TRC records" in result.stdout
    assert "not confirmed: L1/s00001, L1/s00002" in result.stdout
    assert "run the same import again" in result.stderr
