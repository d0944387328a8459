"""Real processes: one query answered by several instances, as a viewer asks every filtering
shard's ``q/state`` at once. The router and the two shards run as processes of their own, as
deployed; this process holds only the asking client."""

from __future__ import annotations

import sys

import zenoh
from support import ready_querier

from services.runtime.config import zenoh_config

READY_S = 30.0
QUERY_S = 60.0  # bounds a stalled run; 10,000 replies of 2 kB take well under a second
PER_SHARD = 5000

# A shard: LatestValues of PER_SHARD states of one line on a queryable; "ready" once declared.
SHARD = """
import sys, threading
import zenoh
from services.runtime.config import zenoh_config
from services.runtime.latest import LatestValues
endpoint, ns, shard, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
latest = LatestValues()
for i in range(n):
    latest.put(f"{ns}/q/state/{shard}001/s{i:05d}", bytes(2000))
settings = {"connect": {"endpoints": [endpoint], "timeout_ms": 30000}}
with zenoh.open(zenoh_config(settings)) as session:
    session.declare_queryable(f"{ns}/q/state/{shard}$*/**", latest.on_query)
    print("ready", flush=True)
    threading.Event().wait()  # until SIGTERM
"""


def test_one_query_answered_by_several_instances_gets_every_reply(
    stack, spawn, free_port, namespace
):
    endpoint, ns = f"tcp/127.0.0.1:{free_port}", namespace
    spawn("router", "router", "--listen", endpoint)
    for shard in "AB":
        argv = [sys.executable, "-c", SHARD, endpoint, ns, shard, str(PER_SHARD)]
        process = spawn(f"shard-{shard}", argv=argv)
        assert process.line(READY_S) == "ready"
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    client = stack.enter_context(zenoh.open(zenoh_config(settings)))
    for shard in "AB":
        stack.callback(ready_querier(client, f"{ns}/q/state/{shard}001/**", READY_S).undeclare)

    # as ServiceRuntime.ask: BLOCK, so that the replies are not dropped when queues fill;
    # a deadline shows as an error reply ("Timeout"), a lost transport as replies missing
    replies = client.get(
        f"{ns}/q/state/**", timeout=QUERY_S, congestion_control=zenoh.CongestionControl.BLOCK
    )
    keys, errors = [], []
    for reply in replies:
        if reply.ok is not None:
            keys.append(str(reply.ok.key_expr))
        else:
            errors.append(reply.err.payload.to_bytes()[:200])
    assert not errors, f"{len(keys)} replies, then error replies {errors[:3]}"
    assert len(keys) == len(set(keys)) == 2 * PER_SHARD
