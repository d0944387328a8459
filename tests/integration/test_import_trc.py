"""`trackfusion import-trc` as a real process: good rows arrive, bad rows are reported."""

from __future__ import annotations

from support import run_cli

from schemas import TrcRecord, decode


def test_import_trc_publishes_good_rows_and_reports_bad_ones(
    open_session, router, namespace, collector, tmp_path
):
    received = collector(lambda sample: decode(sample.payload.to_bytes(), TrcRecord))
    session = open_session()
    subscriber = session.declare_subscriber(f"{namespace}/trc/**", received)
    export = tmp_path / "trc.csv"
    export.write_text(
        "line,segment,t,top6_mm,align10_mm,run_id\n"
        "L1,s00001,2026-03-01T10:00:00Z,4.2,3.1,r1\n"
        "L1,s00002,2026-03-01T10:00:09Z,0,3.1,r1\n"
        "L1,s00003,2026-03-01T10:00:18Z,3.9,2.8,r1\n"
    )
    wiring = ("--connect", router, "--ns", namespace)
    result = run_cli("import-trc", str(export), *wiring, timeout=60)
    assert result.returncode == 1, result.stderr  # bad rows were reported
    assert f"{export}:3: TrcRecord" not in result.stderr  # the reason is the message's own
    assert f"{export}:3:" in result.stderr and "top6_mm" in result.stderr
    assert "published 2 TRC records, 1 bad rows" in result.stdout
    got = sorted((received.get().segment, received.get().segment))
    assert got == ["s00001", "s00003"]
    subscriber.undeclare()
    missing = run_cli("import-trc", str(tmp_path / "nope.csv"), *wiring, timeout=60)
    assert missing.returncode != 0 and "cannot read" in missing.stderr
