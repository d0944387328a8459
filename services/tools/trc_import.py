"""`trackfusion import-trc`: TRC records onto the bus, from a per-segment CSV export
(:func:`main_import_trc_csv`) or, with ``--profile FILE.csv --line L --run-id R --t ISO``,
from a sampled TRC run.

The records are put plainly (no outbox): the command itself then waits until filtering
holds them (:func:`confirm`). Unless ``--no-wait``, it asks ``{ns}/q/state/{line}/{segment}``
for each record's segment until the state's ``last_trc_t`` is the record's ``t`` or later
(a newer TRC record of the segment holds it too: filtering's fold does not depend on the
order of events), puts the records still missing again every ``RESEND_S`` seconds (filtering
refuses a record it already holds), and after ``--wait-s`` seconds at most prints
``confirmed N of M TRC records``, the segments not confirmed, and exits with
``EXIT_UNCONFIRMED``: running the same import again is then the remedy.

The thin part around :mod:`track.trc_profile` (parse, align, statistic per segment): read
the file, take the reference run from the archive, publish one TrcRecord per covered
segment on ``{ns}/trc/{line}/{segment}`` (as ``import-trc FILE.csv`` does) and keep the
aligned profile in the archive for the next run of the line.

The archive (``--archive``, default ``./var/trc-profiles.sqlite``) is a SQLite file with
one row per ``(line, run_id, t)``: the run's profile after alignment, on the network grid
``x_j = j * 0.25 m``. The reference of a run is the latest run of the same line with an
earlier ``t`` that shares at least one alignment window (400 m) with it; a line's first run
(of that stretch) is taken as it is and so sets the chainage datum of the runs after it.
Importing a run that is already in the archive publishes it again and leaves the archive as
it is.

Every record carries ``t`` = ``--t``: a TRC run is one inspection, the time a planner
refers to (the car passes 2 km in about a minute).
"""

from __future__ import annotations

import argparse
import io
import math
import sqlite3
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import zenoh

from schemas import INDICATORS, SchemaError, SegmentState, TrcRecord, decode, encode, keys
from schemas.wire import check_time
from services.defaults import add_network_argument, load_network
from services.runtime.config import RuntimeConfig, config_from_args
from services.tools.operator import (
    RowError,
    add_query_arguments,
    open_session,
    parse_time,
    parse_trc_csv,
)
from services.tools.query import QUERY_TIMEOUT_S
from track.network import check_id
from track.segments import SegmentTable
from track.trc_profile import (
    ALIGN_COLUMNS,
    LEVEL_COLUMNS,
    MAX_OFFSET_M,
    WINDOW_M,
    GridProfile,
    ProfileFileError,
    RunResult,
    TrcProfile,
    parse_profile_csv,
    process_run,
)

WAIT_S = 120.0  # `--wait-s`: the longest the command waits for filtering to hold its records
RESEND_S = 5.0  # seconds between two puts of the records filtering does not hold yet
POLL_S = 1.0  # seconds between two questions to filtering while records are missing
QUERY_BATCH = 256  # q/state questions in flight at once
EXIT_UNCONFIRMED = 3  # some records were not confirmed by filtering within --wait-s


def default_archive() -> Path:
    """``./var/trc-profiles.sqlite``, next to the services' default files (``default_db``)."""
    return Path("var") / "trc-profiles.sqlite"


@dataclass(frozen=True)
class ArchivedRun:
    line: str
    run_id: str
    t: float
    profile: GridProfile


class ProfileArchive:
    """The aligned profiles of the imported runs, one row per ``(line, run_id, t)``."""

    SCHEMA = """
        CREATE TABLE IF NOT EXISTS trc_profile (
            line TEXT NOT NULL,
            run_id TEXT NOT NULL,
            t REAL NOT NULL,               -- epoch s
            first_index INTEGER NOT NULL,  -- chainage of sample 0 = first_index * spacing_m
            spacing_m REAL NOT NULL,
            n INTEGER NOT NULL,
            channels TEXT NOT NULL,        -- comma-separated names, the rows of data
            data BLOB NOT NULL,            -- float64 little-endian, (channels, n) C order
            PRIMARY KEY (line, run_id, t)
        )
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path)
            self._db.execute(self.SCHEMA)
        except (OSError, sqlite3.Error) as exc:
            raise ValueError(f"--archive {path}: cannot open ({exc})") from None

    def close(self) -> None:
        self._db.close()

    def latest_before(
        self, line: str, t: float, span_m: tuple[float, float] = (-math.inf, math.inf)
    ) -> ArchivedRun | None:
        """The reference of a run at ``t`` over chainages ``span_m``: the latest run of
        ``line`` before ``t`` that overlaps the span by at least ``WINDOW_M``."""
        lo, hi = span_m
        row = self._db.execute(
            "SELECT run_id, t, first_index, spacing_m, n, channels, data FROM trc_profile "
            "WHERE line = ? AND t < ? "
            "AND MIN(?, (first_index + n - 1) * spacing_m) - MAX(?, first_index * spacing_m) >= ? "
            "ORDER BY t DESC LIMIT 1",
            (line, t, hi, lo, WINDOW_M),
        ).fetchone()
        if row is None:
            return None
        run_id, t_run, first, dx, n, names, data = row
        values = np.frombuffer(data, dtype="<f8").reshape(-1, n)
        channels = {name: values[i].copy() for i, name in enumerate(names.split(","))}
        return ArchivedRun(line, run_id, t_run, GridProfile(first, dx, channels))

    def add(self, line: str, run_id: str, t: float, profile: GridProfile) -> bool:
        """Keep a run's aligned profile; False when that run is there already."""
        names = list(profile.channels)
        data = np.stack([profile.channels[n] for n in names]).astype("<f8").tobytes()
        with self._db:
            cursor = self._db.execute(
                "INSERT OR IGNORE INTO trc_profile VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (line, run_id, t, profile.first_index, profile.spacing_m, profile.n_samples,
                 ",".join(names), data),
            )  # fmt: skip
        return cursor.rowcount == 1

    def count(self, line: str) -> int:
        return self._db.execute(
            "SELECT COUNT(*) FROM trc_profile WHERE line = ?", (line,)
        ).fetchone()[0]


def trc_records(result: RunResult, line: str, run_id: str, t: float):
    """The TrcRecords of a run, and ``(segment, reason)`` for values no record can carry."""
    records, refused = [], []
    for v in result.values:
        values = (v.top6_mm, v.align10_mm)
        measured = [name for name, x in zip(INDICATORS, values, strict=True) if x is not None]
        try:
            records.append(TrcRecord(line=line, segment=v.segment, t=t, top6_mm=v.top6_mm,
                                     align10_mm=v.align10_mm, run_id=run_id,
                                     indicators=measured))  # fmt: skip
        except SchemaError as exc:
            refused.append((v.segment, str(exc)))
    return records, refused


def indicator_lines(profile: TrcProfile) -> list[str]:
    """What the run's records measure, from which rails, and what they cannot, and why;
    nothing when they measure every indicator on both rails."""
    if set(LEVEL_COLUMNS + ALIGN_COLUMNS) <= set(profile.channels):
        return []
    out = []
    for name, family, columns in (
        ("top6", "longitudinal level", LEVEL_COLUMNS),
        ("align10", "alignment", ALIGN_COLUMNS),
    ):
        rails = [c for c in columns if c in profile.channels]
        if not rails:
            out.append(
                f"{name}: not measured, the file has no {family} column ({', '.join(columns)})"
            )
        elif len(rails) == 1:
            out.append(f"{name}: from {rails[0]} alone (the file has one rail of {family})")
        else:
            out.append(f"{name}: the smaller of {rails[0]} and {rails[1]}")
    return out


def format_report(
    path: str,
    profile: TrcProfile,
    result: RunResult,
    line: str,
    run_id: str,
    reference: ArchivedRun | None,
    n_records: int,
    refused: list[tuple[str, str]],
) -> str:
    """What the operator reads: the run (``line``: its id, and name), what its records
    measure when not every indicator on both rails, its alignment per window, the
    segments."""
    x0, x1 = profile.chainage_m[0], profile.chainage_m[-1]
    if profile.descending:
        x0, x1 = x1, x0
    out = [
        f"run {run_id} on line {line}: {path}, {profile.n_samples} samples, "
        f"{profile.direction}, chainage {x0:.2f} -> {x1:.2f} m, "
        f"channels {', '.join(profile.channels)}"
    ]
    if profile.ignored_columns:
        out.append(f"ignored columns: {', '.join(profile.ignored_columns)}")
    out.extend(indicator_lines(profile))
    if reference is None:
        out.append(
            "alignment: no earlier run of this stretch of the line in the archive, taken as it is"
        )
    elif result.alignment.identity:
        out.append(f"alignment: skipped (--no-align); reference would be run {reference.run_id}")
    else:
        used = result.alignment.used
        on = "" if result.alignment.signal == "level" else ", matched on alignment"
        out.append(
            f"alignment to run {reference.run_id} (offset = its chainage - this run's{on}): "
            f"{len(used)} of {len(result.alignment.windows)} windows used"
        )
        out.append(f"  {'window start m':>14} {'offset m':>9} {'peak':>6}")
        for w in result.alignment.windows:
            state = "used" if w.used else f"rejected: {w.reason}"
            out.append(f"  {w.start_m:14.2f} {w.offset_m:9.3f} {w.peak:6.3f}  {state}")
    published = [v.segment for v in result.values if v.segment not in dict(refused)]
    span = f" ({published[0]} .. {published[-1]})" if published else ""
    out.append(f"segments: {n_records} with a record{span}")
    if result.partial:
        out.append(
            f"skipped, not fully covered by the run: {len(result.partial)} "
            f"({', '.join(result.partial)})"
        )
    if result.outside:
        out.append(f"skipped, outside the run: {len(result.outside)}")
    for segment, reason in refused:
        out.append(f"skipped, no record can carry its value: {segment}: {reason}")
    return "\n".join(out)


def publish(session: zenoh.Session, ns: str, records: list[TrcRecord]) -> None:
    for record in records:
        session.put(
            keys.trc(ns, record.line, record.segment),
            encode(record),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )


def held(state: SegmentState | None, record: TrcRecord) -> bool:
    """Whether filtering's state of the record's segment has folded the record: its last
    TRC restart is at the record's time or later."""
    return state is not None and state.last_trc_t is not None and state.last_trc_t >= record.t


def query_segment_states(
    session: zenoh.Session, ns: str, segments: list[tuple[str, str]], timeout: float
) -> dict[tuple[str, str], SegmentState]:
    """The state filtering answers for each of ``segments`` on ``q/state/{line}/{segment}``;
    a segment without an answer (no instance owns it, none is up, no complete answer in
    ``timeout``) is left out. Of several answers, the one with the latest TRC restart."""
    out: dict[tuple[str, str], SegmentState] = {}
    block = zenoh.CongestionControl.BLOCK
    for start in range(0, len(segments), QUERY_BATCH):
        asked = [
            session.get(
                keys.q_state_keys(ns, f"{line}/{segment}"),
                timeout=timeout,
                congestion_control=block,
            )
            for line, segment in segments[start : start + QUERY_BATCH]
        ]
        for replies in asked:
            for reply in replies:
                if reply.ok is None:
                    continue
                state = decode(reply.ok.payload.to_bytes(), SegmentState)
                sid = (state.line, state.segment)
                if sid not in out or (state.last_trc_t or -math.inf) > (
                    out[sid].last_trc_t or -math.inf
                ):
                    out[sid] = state
    return out


def confirm(
    session: zenoh.Session,
    ns: str,
    records: list[TrcRecord],
    wait_s: float,
    out: TextIO = sys.stdout,
) -> int:
    """Wait until filtering holds every one of ``records`` (published already), putting
    the missing ones again every ``RESEND_S`` s; print what was confirmed. 0 when every
    record was, else ``EXIT_UNCONFIRMED`` with what to do on stderr."""
    if not records:
        return 0  # nothing published: nothing to wait for
    print(
        f"waiting up to {wait_s:g} s for filtering to confirm {len(records)} TRC records",
        file=out,
        flush=True,
    )
    deadline = time.monotonic() + wait_s
    resend_at = time.monotonic() + RESEND_S
    missing = list(records)
    while missing:
        segments = sorted({(r.line, r.segment) for r in missing})
        left = deadline - time.monotonic()
        states = query_segment_states(session, ns, segments, max(1.0, min(QUERY_TIMEOUT_S, left)))
        missing = [r for r in missing if not held(states.get((r.line, r.segment)), r)]
        now = time.monotonic()
        if not missing or now >= deadline:
            break
        if now >= resend_at:
            publish(session, ns, missing)
            resend_at = now + RESEND_S
        time.sleep(min(POLL_S, deadline - now))
    print(f"confirmed {len(records) - len(missing)} of {len(records)} TRC records", file=out)
    if not missing:
        return 0
    segments = sorted({f"{r.line}/{r.segment}" for r in missing})
    print(f"not confirmed: {', '.join(segments)}", file=out)
    print(
        f"filtering did not confirm {len(missing)} TRC records within {wait_s:g} s: check "
        "that a filtering instance owns those segments and is up (`trackfusion status`), "
        "then run the same import again (filtering refuses the records it holds already)",
        file=sys.stderr,
    )
    return EXIT_UNCONFIRMED


def main_import_trc_csv(
    conf: RuntimeConfig,
    path: str,
    *,
    wait_s: float | None = WAIT_S,
    out: TextIO = sys.stdout,
) -> int:
    """Publish the good rows of a TRC CSV export, report bad rows with their line numbers,
    and (``wait_s`` not None) wait for filtering to confirm the records."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SystemExit(f"import-trc: cannot read {path}: {exc}") from None
    records, errors = [], []
    for item in parse_trc_csv(io.StringIO(text, newline="")):
        (errors if isinstance(item, RowError) else records).append(item)
    for error in errors:
        print(f"{path}:{error.line_no}: {error.reason}", file=sys.stderr)
    with open_session(conf) as session:
        publish(session, conf.ns, records)
        print(f"published {len(records)} TRC records, {len(errors)} bad rows", file=out, flush=True)
        code = 0 if wait_s is None else confirm(session, conf.ns, records, wait_s, out)
    return code or (1 if errors else 0)


@contextmanager
def _archive(path: Path) -> Iterator[ProfileArchive]:
    archive = ProfileArchive(path)
    with closing(archive):
        yield archive


def main_import_trc_profile(
    conf: RuntimeConfig,
    path: str,
    line: str,
    run_id: str,
    t: float,
    *,
    network_path: str | None = None,
    archive_path: str | Path | None = None,
    align: bool = True,
    max_offset_m: float = MAX_OFFSET_M,
    dry_run: bool = False,
    wait_s: float | None = WAIT_S,
    out: TextIO = sys.stdout,
) -> int:
    """Parse, align, compute and (unless ``dry_run``) publish and archive one TRC run, then
    (``wait_s`` not None) wait for filtering to confirm its records."""
    check_id("--line", line)
    check_id("--run-id", run_id)
    network = load_network(network_path)
    table = SegmentTable.from_network(network)
    if line not in table.lines:
        raise ValueError(f"--line {line}: not a line of the network ({', '.join(table.lines)})")
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--profile {path}: cannot read ({exc})") from None
    try:
        profile = parse_profile_csv(text)
    except ProfileFileError as exc:
        for line_no, reason in exc.problems:
            print(f"{path}:{line_no}: {reason}", file=sys.stderr)
        raise ValueError(f"--profile {path}: {exc}; nothing imported") from None
    archive_file = Path(archive_path or default_archive())
    with ExitStack() as stack:
        archive = None  # a dry run creates no archive
        if archive_file.exists() or not dry_run:
            archive = stack.enter_context(_archive(archive_file))
        span = (float(profile.chainage_m[0]), float(profile.chainage_m[-1]))
        reference = archive.latest_before(line, t, span) if archive else None
        result = process_run(
            profile,
            table.lines[line],
            reference.profile if reference else None,
            align=align,
            max_offset_m=max_offset_m,
        )
        records, refused = trc_records(result, line, run_id, t)
        name = network.lines[line].name
        label = f"{line} ({name})" if name and name != line else line
        print(
            format_report(path, profile, result, label, run_id, reference, len(records), refused),
            file=out,
        )
        if dry_run or archive is None:
            print("dry run: nothing published, nothing archived", file=out)
            return 0
        with open_session(conf) as session:
            publish(session, conf.ns, records)
            # archived once published, confirmed or not: importing the run again (what an
            # unconfirmed import asks for) keeps the archive as it is and still publishes
            kept = archive.add(line, run_id, t, result.grid)
            print(
                f"published {len(records)} TRC records; "
                + (f"profile archived in {archive.path}" if kept else "run already in the archive"),
                file=out,
                flush=True,
            )
            return 0 if wait_s is None else confirm(session, conf.ns, records, wait_s, out)


def add_profile_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of the ``--profile`` form of ``import-trc``."""
    group = parser.add_argument_group(
        "a sampled TRC run (--profile): aligned to the line's previous run, Top6/Align10 "
        "computed per segment; the CSV format is in README.md, section TRC profiles"
    )
    group.add_argument("--profile", metavar="FILE.csv", help="the run's profile export")
    group.add_argument("--line", help="line id of the run (of --network)")
    group.add_argument("--run-id", help="id of the run, carried by its TrcRecords")
    group.add_argument("--t", metavar="ISO", help="time of the run: ISO 8601 or epoch s")
    add_network_argument(group, "the segments")
    group.add_argument(
        "--archive",
        metavar="FILE",
        type=Path,
        help=f"aligned profiles of earlier runs (default: ./{default_archive()})",
    )
    group.add_argument(
        "--max-offset",
        type=float,
        default=MAX_OFFSET_M,
        metavar="M",
        help="search the offset to the previous run within +-M metres (default %(default)g)",
    )
    group.add_argument("--no-align", action="store_true", help="take the run's chainage as it is")
    group.add_argument(
        "--dry-run", action="store_true", help="print the report; publish and archive nothing"
    )


def run_profile(args: argparse.Namespace, conf: RuntimeConfig) -> int:
    missing = [flag for flag in ("line", "run_id", "t") if getattr(args, flag) is None]
    if missing:
        flags = ", ".join("--" + m.replace("_", "-") for m in missing)
        raise ValueError(f"--profile needs {flags}")
    if not 0 < args.max_offset <= 200:
        raise ValueError(f"--max-offset {args.max_offset:g}: give metres in (0, 200]")
    try:
        t = parse_time(args.t)
        check_time("--t", t)
    except SchemaError as exc:
        raise ValueError(str(exc)) from None
    except ValueError:
        raise ValueError(f"--t {args.t!r}: not an ISO 8601 time nor epoch seconds") from None
    return main_import_trc_profile(
        conf,
        args.profile,
        args.line,
        args.run_id,
        t,
        network_path=args.network,
        archive_path=args.archive,
        align=not args.no_align,
        max_offset_m=args.max_offset,
        dry_run=args.dry_run,
        wait_s=wait_seconds(args),
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Publish every good row of a TRC CSV export as a TrcRecord; bad rows are reported "
        "with their line numbers (exit code 1 when there were any). With --profile, a "
        "sampled TRC run instead: aligned to the line's previous run, Top6/Align10 computed "
        "per segment, published and archived. Then wait until filtering confirms it holds "
        "every record."
    )
    parser.add_argument("file", metavar="FILE.csv", nargs="?", help="per-segment TRC export")
    add_profile_arguments(parser)
    group = parser.add_argument_group(
        "confirmation: after publishing, wait until filtering holds every record (its "
        f"q/state), putting the missing ones again every {RESEND_S:g} s; exit code "
        f"{EXIT_UNCONFIRMED} when some are still missing"
    )
    group.add_argument(
        "--wait-s",
        type=float,
        default=WAIT_S,
        metavar="S",
        help="wait at most S seconds (default: %(default)g)",
    )
    group.add_argument(
        "--no-wait", action="store_true", help="publish and exit, without confirmation"
    )
    add_query_arguments(parser, timeout=False)


def wait_seconds(args: argparse.Namespace) -> float | None:
    """``--wait-s``, None with ``--no-wait``."""
    if args.no_wait:
        return None
    if not 0 < args.wait_s < math.inf:
        raise ValueError(f"--wait-s {args.wait_s:g}: give a number of seconds > 0")
    return args.wait_s


def run(args: argparse.Namespace) -> int:
    if (args.file is None) == (args.profile is None):
        raise ValueError("give either FILE.csv (per-segment values) or --profile FILE.csv")
    if args.profile is not None:
        return run_profile(args, config_from_args(args))
    return main_import_trc_csv(config_from_args(args), args.file, wait_s=wait_seconds(args))
