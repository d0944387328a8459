"""Every documented command line parses, to the options it says.

The lines come from where users and operators copy them: the shell blocks of the Markdown
files, the Makefile, the systemd units (with the example environment of their comments), the
compose file and the stack file (as ``up`` builds them). Each must parse; each flag it gives
must land in the option of that name with that value; and the whole parsed namespace, the
defaults included, must equal the one recorded in ``cli_lines.json``. After a deliberate
change to the command line, rewrite that file with
``python tests/unit/test_cli_lines.py --update`` and read its diff.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from services.cli import COMMANDS, build_parser
from services.defaults import default_file
from services.tools.stack import load_stack

REPO = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).with_name("cli_lines.json")
# The example environment of deploy/systemd/trackfusion@.service (its comment).
UNIT_ENV = {
    "TRACKFUSION_COMMAND": "filtering",
    "TRACKFUSION_ARGS": "--db /var/lib/trackfusion/filtering.sqlite --instance site1",
}


PLACEHOLDERS = re.compile(r"^([A-Z]|[A-Z]+\.\w+)$")  # N, S, F.geojson: a synopsis


def _markdown_lines() -> list[tuple[str, list[str]]]:
    """``trackfusion …`` lines of the ```sh blocks, and the inline ``trackfusion --…`` spans
    that are whole command lines (synopses with ``[…]``, ``…``, ``|`` or ``N`` left out)."""
    files = subprocess.run(
        ["git", "ls-files", "*.md"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout.split()
    found = []
    for name in sorted(files):
        text = (REPO / name).read_text()
        lines = [
            line
            for block in re.findall(r"```sh\n(.*?)```", text, flags=re.S)
            for line in block.replace("\\\n", " ").splitlines()
        ]
        spans = re.findall(r"`((?:\.venv/bin/)?trackfusion [^`]*--[^`]*)`", text)
        for line in [*lines, *(" ".join(span.split()) for span in spans)]:
            words = shlex.split(line.split(" #")[0].strip(), posix=True)
            if not words or Path(words[0]).name != "trackfusion":
                continue
            if any(c in line for c in "[…|") or any(PLACEHOLDERS.match(w) for w in words):
                continue
            words = words[1 : words.index(">")] if ">" in words else words[1:]
            found.append((f"{name}: {line.strip()}", [w for w in words if w != "&"]))
    return found


def _makefile_lines() -> list[tuple[str, list[str]]]:
    lines = (REPO / "Makefile").read_text().splitlines()
    return [
        (f"Makefile: {line.strip()}", shlex.split(line.split("/trackfusion", 1)[1]))
        for line in lines
        if "$(BIN)/trackfusion " in line
    ]


def _systemd_lines() -> list[tuple[str, list[str]]]:
    found = []
    for unit in sorted((REPO / "deploy" / "systemd").glob("*.service")):
        for line in unit.read_text().splitlines():
            if line.startswith("ExecStart="):
                command = line.split("/trackfusion ", 1)[1]
                for name, value in UNIT_ENV.items():
                    command = command.replace(f"${name}", value)
                found.append((f"deploy/systemd/{unit.name}: {line}", shlex.split(command)))
    return found


def _compose_lines() -> list[tuple[str, list[str]]]:
    services = yaml.safe_load((REPO / "deploy" / "compose.yaml").read_text())["services"]
    return [
        (f"deploy/compose.yaml: {name}", [str(w) for w in service["command"]])
        for name, service in services.items()
        if service.get("image", "").startswith("trackfusion")
    ]


def _stack_lines() -> list[tuple[str, list[str]]]:
    stack = load_stack(default_file("stack.json5"))
    wiring = ["--connect", stack.listen, "--ns", stack.ns]
    return [
        (f"services/defaults/stack.json5: {p.name}", [p.command, *wiring, *p.args])
        for p in stack.processes
    ]


LINES = [
    *_markdown_lines(),
    *_makefile_lines(),
    *_systemd_lines(),
    *_compose_lines(),
    *_stack_lines(),
]


def _plain(value: Any) -> Any:
    """JSON-able, with paths in the repository written relative to it."""
    if isinstance(value, Path | str) and str(value).startswith(str(REPO) + "/"):
        return Path(value).relative_to(REPO).as_posix()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def parsed(words: list[str]) -> dict[str, Any]:
    args = build_parser().parse_args(words)
    return {k: _plain(v) for k, v in sorted(vars(args).items()) if not callable(v)}


def test_every_source_gives_lines():
    sources = {where.split(":")[0].split("/")[0] for where, _ in LINES}
    assert {"README.md", "Makefile", "deploy"} <= sources
    assert len(LINES) >= 30


@pytest.mark.parametrize(("where", "words"), LINES, ids=[w for w, _ in LINES])
def test_documented_line_parses_to_its_options(where, words):
    options = parsed(words)
    for flag, value in zip(words, words[1:], strict=False):
        if not flag.startswith("--") or value.startswith("--"):
            continue
        dest = flag.removeprefix("--").replace("-", "_")
        if dest not in options or isinstance(options[dest], bool):
            continue
        got = options[dest]
        if isinstance(got, list):
            assert value in got, (where, flag)
        elif isinstance(got, int | float) and not isinstance(got, bool):
            assert got == float(value), (where, flag)
        else:
            assert str(got) == _plain(value), (where, flag)
    golden = json.loads(GOLDEN.read_text())
    assert where in golden, f"new line: run python {Path(__file__).relative_to(REPO)} --update"
    assert options == golden[where]


def _command_paths(commands, prefix=()):
    for command in commands:
        path = (*prefix, command.name)
        yield from _command_paths(command.subcommands, path) if command.subcommands else [path]


@pytest.mark.parametrize("path", list(_command_paths(COMMANDS)), ids=" ".join)
def test_every_command_declares_its_arguments_and_run(path, capsys):
    """Its module has ``add_arguments`` and ``run`` (looked up when the command is parsed)
    and the parser they build prints its help."""
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args([*path, "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: trackfusion {' '.join(path)}")


def test_golden_file_has_no_stale_lines():
    assert sorted(json.loads(GOLDEN.read_text())) == sorted(where for where, _ in LINES)


if __name__ == "__main__" and sys.argv[1:] == ["--update"]:
    GOLDEN.write_text(json.dumps({w: parsed(words) for w, words in LINES}, indent=1) + "\n")
