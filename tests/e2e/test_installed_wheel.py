"""A non-editable install runs from any directory: the default files (network, router and
simulator configs, study config, …) are package data found through importlib.resources.

The wheel is built from a copy of the sources, installed with ``pip install --target`` into
a directory of its own, and run by an interpreter that cannot see this checkout: ``-I``
(no PYTHONPATH, no working directory on sys.path) and ``-S`` (no .pth files, so not the
editable install's finder), with sys.path = that directory + the venv's site-packages for
the dependencies. Every command runs in an empty directory.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SOURCES = ("pyproject.toml", "README.md", "schemas", "services", "simulators", "track")
TIMEOUT_S = 60.0


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The directory the wheel was installed into."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    src.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, src / name)
    pip = [sys.executable, "-m", "pip", "-q", "--disable-pip-version-check"]
    # with build isolation: the build backend pyproject.toml asks for, whatever the venv has
    subprocess.run([*pip, "wheel", "--no-deps", "-w", root / "dist", src], check=True)
    (wheel,) = (root / "dist").glob("trackfusion-*.whl")
    target = root / "target"
    subprocess.run([*pip, "install", "--no-deps", "--target", target, wheel], check=True)
    return target


def isolated(target: Path, code: str) -> list[str]:
    """A command line running ``code`` with only ``target`` and the dependencies importable."""
    paths = [str(target), sysconfig.get_paths()["purelib"]]
    return [sys.executable, "-I", "-S", "-c", f"import sys; sys.path[:0] = {paths!r}; {code}"]


def trackfusion(target: Path, *args: str) -> list[str]:
    """The installed console script ``trackfusion ARGS…``."""
    script = str(target / "bin" / "trackfusion")
    argv = ["trackfusion", *args]
    code = f"sys.argv = {argv!r}; import runpy; runpy.run_path({script!r}, run_name='__main__')"
    return isolated(target, code)


def test_the_installed_package_is_the_one_imported(installed, tmp_path):
    code = (
        "import services, schemas, simulators, services.defaults as d; "
        "print(services.__file__, schemas.__file__, simulators.__file__, "
        "d.default_file('demo-network.geojson'), sys.meta_path)"
    )
    done = subprocess.run(
        isolated(installed, code), cwd=tmp_path, capture_output=True, text=True, check=True
    )
    *files, meta_path = done.stdout.split(" ", 4)
    assert all(Path(f).is_relative_to(installed) for f in files), done.stdout
    assert "__editable__" not in meta_path


def test_help_and_commands_that_read_the_default_files(installed, tmp_path, free_port, spawn):
    cwd = tmp_path / "run"  # empty: nothing may be written where the commands run
    cwd.mkdir()
    run = {"cwd": cwd, "capture_output": True, "text": True, "timeout": TIMEOUT_S}
    helped = subprocess.run(trackfusion(installed, "--help"), **run)
    assert helped.returncode == 0 and helped.stdout.startswith("usage: trackfusion"), helped

    # the frequency study on its packaged config
    study = subprocess.run(
        trackfusion(installed, "study", "frequency", "--paths", "8", "--json", "--no-progress"),
        **run,
    )
    assert study.returncode == 0, study.stderr
    assert json.loads(study.stdout)

    # the router on its packaged config; the simulator on the packaged demo network and
    # simulator config, publishing to it and exiting
    endpoint = f"tcp/127.0.0.1:{free_port}"
    router = spawn("router", argv=trackfusion(installed, "router", "--listen", endpoint), cwd=cwd)
    router.until(lambda: "listening on" in router.log_path.read_text(), TIMEOUT_S, "listening")
    started = router.log_path.read_text()
    assert "Error" not in started[: started.index("listening on")], router.log()
    simulated = subprocess.run(
        trackfusion(
            installed, "simulate", "--fidelity", "index", "--days", "2", "--trains", "1",
            "--speedup", "inf", "--connect", endpoint, "--no-progress",
        ),
        **run,
    )  # fmt: skip
    assert simulated.returncode == 0, simulated.stderr
    published = json.loads(simulated.stdout.splitlines()[-1])
    assert published["by_type"]["OnboardIndex"] > 0, published  # passes over the demo lines
    router.signal(signal.SIGINT)
    assert router.wait(TIMEOUT_S) == 0, router.log()
    assert list(cwd.iterdir()) == []  # nothing written where it was run
