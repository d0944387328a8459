"""schemas/README.md, "The gateway contract": its worked example, run as written, passes
ingestion's checks; so does the key-table section's example."""

from __future__ import annotations

import re
from pathlib import Path

from schemas import GpsFix, RawChunk
from services.defaults import demo_network
from services.ingestion.core import IngestionCore, Rejection
from services.ingestion.service import decode_gateway
from services.tools.gateway_check import GatewayCheck

README = Path(__file__).resolve().parents[2] / "schemas" / "README.md"


def _example(heading: str) -> dict:
    """Run the first python block after ``heading``; its variables."""
    text = README.read_text()
    block = re.search(r"```python\n(.*?)```", text[text.index(heading) :], re.S)
    assert block, f"no python example after {heading!r}"
    code = block.group(1).replace("session.put", "# session.put")
    variables: dict = {}
    exec(compile(code, str(README), "exec"), variables)  # the documentation's own code
    return variables


def test_the_worked_example_is_accepted():
    example = _example("### Worked example")
    chunk = decode_gateway("raw", "tf/raw/T17/bogie1", example["chunk"])
    fix = decode_gateway("gps", "tf/gps/T17", example["fix"])
    assert isinstance(chunk, RawChunk) and isinstance(fix, GpsFix)
    core = IngestionCore(demo_network())
    # held for its position (the fix is not on the demo network), never refused
    assert [o for o in core.step(chunk) + core.step(fix) if isinstance(o, Rejection)] == []
    check = GatewayCheck("T17")  # arriving live: the receiver's clock just after the data
    check.feed("raw", "tf/raw/T17/bogie1", example["chunk"], fix.t + 1.0)
    check.feed("gps", "tf/gps/T17", example["fix"], fix.t + 1.1)
    report, code = check.report()
    assert code == 0, report


def test_the_key_table_example_is_accepted():
    example = _example("## Example: a gateway in another language")
    chunk = decode_gateway("raw", "tf/raw/T17/bogie1", example["payload"])
    assert [o for o in IngestionCore(demo_network()).step(chunk) if isinstance(o, Rejection)] == []
