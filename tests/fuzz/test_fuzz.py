"""Bad-input fuzzing of every subscribing service, in-process on a real router.

For each service: a clean run of a fixed sequence of valid traffic, then a run of the same
valid traffic interleaved with ``TF_FUZZ_N`` bad messages (default 10,000) on the service's
input keys: random bytes, valid MessagePack of the wrong types or shapes, missing fields,
NaN and inf in floats and arrays, huge declared arrays, unknown versions, keys disagreeing
with the payload or with unexpected chunks, out-of-range values and truncated payloads. It
checks that

- the service is still alive at the end (its worker thread runs, its liveliness token is
  there) and stops cleanly with exit code 0;
- every bad message produced exactly one dead letter with a non-empty reason on
  ``{ns}/deadletter/{service}`` (counted by key, so a kind of bad input that is silently
  accepted or dropped shows up by name in the failure);
- the results of the valid traffic (published outputs, in order, and the queryables'
  answers) are byte-identical to the clean run's.

End of input is detected with *markers*: a payload of one never-used MessagePack byte
(0xc1) and a counter, which every service refuses; each service handles its inputs in one
worker thread, in order, so once a marker's dead letter is back everything put before it
has been handled (and, once the service's reliable publishers are flushed and one more
marker is back, everything it put for it has arrived). The clean run uses the same markers
at the same places (they come after the valid message they follow, so they cannot change
its result); they are counted among the fuzz run's bad messages.

Each valid message is followed by a marker on its own key, and the next valid message waits
for that marker's letter. This makes the clean run reproducible: zenoh-python runs each
subscriber's callback on its own thread, so messages on keys of *different* subscriptions
of one service can be handled in another order than they were put (seen: 153 inversions in
2,000 puts over four subscriptions), and the calibration core refits per batch the worker
takes from its queue. Bad messages are still interleaved freely between the valid ones.
Bad messages are sent with at most ``WINDOW`` of them
unanswered by a dead letter (flow control: the viewer's subscriptions are ring buffers that
drop the oldest when it falls behind, by design, and dead letters are put with Zenoh's
default congestion control). No sleeps: every wait is a queue read with a timeout.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh
from fuzz_harness import (
    MARKER,
    N_BAD,
    first_difference,
    run_service,
    stored_bytes,
    strip,
    unlettered,
)
from fuzz_specs import SPECS, RecordingCore

from services.filtering import service as filtering
from services.runtime.config import RuntimeConfig
from services.viewer import service as viewer


@pytest.fixture
def viewer_records(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(viewer, "ViewerCore", RecordingCore)


@pytest.mark.parametrize("name", list(SPECS))
def test_bad_input_is_dead_lettered_and_changes_nothing(
    name: str,
    router: str,
    namespace: str,
    open_session: Callable[..., zenoh.Session],
    tmp_path: Path,
    viewer_records: None,
):
    session = open_session()

    def conf(suffix: str) -> RuntimeConfig:
        return RuntimeConfig(
            ns=f"{namespace}{suffix}",
            instance="test",
            zenoh={"mode": "client", "connect": {"endpoints": [router]}},
        )

    clean_spec = SPECS[name](f"{namespace}c")
    clean, clean_sent = run_service(clean_spec, conf("c"), session, tmp_path / "clean", 0)
    fuzz_spec = SPECS[name](f"{namespace}f")
    n_bad = max(0, N_BAD - len(clean_sent))  # the markers count among the bad messages
    fuzz, sent = run_service(fuzz_spec, conf("f"), session, tmp_path / "fuzz", n_bad)

    # every bad message (markers included) has exactly one dead letter with a reason
    assert all(letter.reason.strip() for letter in fuzz.letters)
    assert all(letter.service == name for letter in fuzz.letters)
    ns = f"{namespace}f"
    by_key_sent = Counter(strip(ns, b.key) for b in sent if b.kind != "marker")
    by_key_got = Counter(
        strip(ns, letter.key)
        for letter in fuzz.letters
        if not letter.payload_head.startswith(MARKER)
    )
    assert by_key_got == by_key_sent, (
        f"{name}: {len(fuzz.letters)} dead letters for {len(sent)} bad messages; "
        f"without a letter: {unlettered(sent, fuzz.letters, ns)}"
    )
    assert len(fuzz.letters) == len(sent) == max(N_BAD, len(clean_sent))

    # the valid traffic's results are those of the clean run, byte for byte
    difference = first_difference(clean.outputs, fuzz.outputs)
    assert fuzz.outputs == clean.outputs, f"{name}: outputs differ from the clean run: {difference}"
    assert fuzz.answers == clean.answers, f"{name}: queryable answers differ from the clean run"
    if name == viewer.SERVICE:
        # A display is latest-only: its inbox replaces a held message by a newer one of the
        # same segment and day (and GPS fix of the same train) when they come faster than it
        # draws, so how many of the earlier ones it logged depends on timing. What must
        # hold: it logged only valid messages, the newest of each key in both runs, and the
        # same entities.
        valid = {payload for _, payload in clean_spec.valid}
        newest = set(dict(clean_spec.valid).values())
        for run in (clean, fuzz):
            assert set(run.logged) <= valid, f"{name}: logged a message it was not sent"
            assert newest <= set(run.logged), f"{name}: the newest of a key was not logged"
        assert fuzz.rrd.keys() == clean.rrd.keys() and clean.rrd
    else:
        assert fuzz.logged == clean.logged, f"{name}: logged messages differ from the clean run"
        assert clean.outputs, f"{name}: the valid traffic gave no output to compare"
    if name == filtering.SERVICE:  # unknown fields are not stored: the same bytes as clean
        assert stored_bytes(tmp_path / "fuzz") == stored_bytes(tmp_path / "clean")
