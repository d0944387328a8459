"""bench/scale.py's network: four regions of equal size whose line ids each region
selector takes, readable back as a network with every segment."""

from __future__ import annotations

import zenoh

from bench.scale import REGIONS, write_network
from schemas import keys
from track.network import Network


def test_the_scale_network_splits_into_four_equal_regions(tmp_path):
    path = tmp_path / "net.geojson"
    made = write_network(4_000, path, seed=3)
    network = Network.from_geojson(path)
    assert made["segments"] == network.n_segments == 4_000
    assert made["per_region"] == dict.fromkeys(REGIONS, 1_000)
    for region in REGIONS:
        selector = zenoh.KeyExpr(keys.segment_keys("tf", "index", f"{region}$*/**"))
        owned = [
            line_id
            for line_id in network.lines
            if selector.includes(zenoh.KeyExpr(keys.index("tf", line_id, "s0")))
        ]
        assert len(owned) == 2 and all(line_id.startswith(region) for line_id in owned)
