"""Maintenance detection is a function of the segment's events, not of their order of
arrival: seeded random sequences (TRC runs, unreported tampings under the indices, known and
interval reports and corrections, ties) delivered shuffled, duplicated and late, one message
at a time, in batches, and after a restart from the store, end in the bytes of the canonical
order; the detections and withdrawals the batches publish, folded by a consumer in a shuffled
order, leave the canonical detected tampings (``bench/order_check.py`` runs many more)."""

from __future__ import annotations

from collections import Counter

from bench.order_check import check


def test_every_delivery_of_a_sequence_ends_in_the_canonical_state(tmp_path):
    seen: Counter = Counter()
    for seed in (0, 1, 3, 4, 8, 9):
        assert check(seed, 3, tmp_path, seen) == []
    # the deliveries made detections, and late events withdrew some of them
    assert seen["detected"] > 0 and seen["withdrawn"] > 0
