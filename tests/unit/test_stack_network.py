"""`trackfusion up --network FILE`: ``{network}`` in the stack file's args is that file for
every process that reads a network, the demo network without the flag."""

from __future__ import annotations

import json5
import pytest

from services.cli import build_parser
from services.cli import main as cli_main
from services.defaults import default_file
from services.tools.stack import load_stack

DEFAULT_STACK = default_file("stack.json5")


def network_options(stack) -> dict[str, str | None]:
    """``--network`` of each process of the stack that has the option, as parsed."""
    found = {}
    for p in stack.processes:
        args = build_parser().parse_args([p.command, *p.args])
        if hasattr(args, "network"):
            found[p.name] = None if args.network is None else str(args.network)
    return found


def test_every_process_of_the_default_stack_reads_the_network_given(tmp_path):
    network = tmp_path / "network.geojson"
    options = network_options(load_stack(DEFAULT_STACK, network=network))
    assert set(options) == {
        "calibration", "filtering", "alerting", "planning", "ingestion", "extraction",
        "viewer", "simulator", "fleet",
    }  # fmt: skip
    assert set(options.values()) == {str(network)}


def test_without_the_flag_they_read_the_demo_network():
    options = network_options(load_stack(DEFAULT_STACK))
    assert set(options.values()) == {str(default_file("demo-network.geojson"))}


def test_a_stack_without_the_placeholder_refuses_a_network(tmp_path):
    stack_file = tmp_path / "stack.json5"
    stack_file.write_text(
        json5.dumps(
            {"router": {"listen": "tcp/127.0.0.1:7447"}, "processes": [{"name": "ingestion"}]}
        )
    )
    assert load_stack(stack_file).processes[0].args == ()
    with pytest.raises(ValueError, match=r"has no \{network\}"):
        load_stack(stack_file, network=tmp_path / "n.geojson")


def test_up_with_a_bad_network_file_exits_2_before_starting_anything(tmp_path, capsys):
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": []}')
    state_dir = tmp_path / "var"
    stack_file = tmp_path / "stack.json5"
    stack_file.write_text(
        json5.dumps(
            {
                "router": {"listen": "tcp/127.0.0.1:1"},
                "state_dir": str(state_dir),
                "processes": [{"name": "ingestion", "args": ["--network", "{network}"]}],
            }
        )
    )
    code = cli_main(["up", "--stack", str(stack_file), "--network", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and str(bad) in err and "no LineString line features" in err
    assert not state_dir.exists()
