"""`trackfusion simulate` as a real process through a real router: everything it says it
published arrives and decodes, and the ground-truth file holds the same records."""

from __future__ import annotations

import json
import threading

import zenoh

from schemas import OnboardIndex, TrcRecord, decode, keys
from simulators.groundtruth import load_truth


def test_simulate_index_fidelity_publishes_everything(
    open_session, router, namespace, spawn, tmp_path
):
    received: dict[str, int] = {}
    bad: list[str] = []
    arrived = threading.Condition()

    def on_sample(sample: zenoh.Sample) -> None:
        kind = keys.kind(sample.key_expr)
        try:
            if kind == "index":
                decode(sample.payload.to_bytes(), OnboardIndex)
            elif kind == "trc":
                decode(sample.payload.to_bytes(), TrcRecord)
        except ValueError as exc:
            bad.append(str(exc))
        with arrived:
            received[kind] = received.get(kind, 0) + 1
            arrived.notify_all()

    session = open_session()
    subscriber = session.declare_subscriber(f"{namespace}/**", on_sample)
    truth = tmp_path / "truth.sqlite"
    process = spawn(
        "simulate",
        "simulate", "--fidelity", "index",
        "--days", "20", "--trains", "2", "--speedup", "inf", "--seed", "5",
        "--connect", router, "--ns", namespace, "--truth", str(truth), "--no-progress",
    )  # fmt: skip
    assert process.wait(120) == 0, process.log()
    out = process.stdout()
    summary = json.loads(out.strip().splitlines()[-1])
    published = summary["published"]
    assert published > 1000 and summary["by_type"]["OnboardIndex"] > 0
    # Puts are reliable and blocking: the subscriber sees them all (the last may still be
    # on their way when the process has exited).
    with arrived:
        arrived.wait_for(lambda: sum(received.values()) - received.get("alive", 0) >= published, 10)
        data = {k: v for k, v in received.items() if k != "alive"}
    subscriber.undeclare()
    assert sum(data.values()) == published, (data, summary)
    assert not bad
    recorded = load_truth(truth)
    assert len(recorded["trc_t"]) == summary["by_type"]["TrcRecord"]
    assert len(recorded["onboard_t"]) == summary["by_type"]["OnboardIndex"]
