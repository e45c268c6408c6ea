"""The package as a user installs it: a wheel built from the project, installed into a folder of its
own, run from an empty folder with nothing of the checkout on the path."""

import json
import os
import shutil
import subprocess
import sys
from importlib import metadata

import pytest

from scenario_files import REPO

# what the wheel is built from (the build writes build/ and *.egg-info into its copy, not the checkout)
PROJECT_FILES = ("pyproject.toml", "README.md", "src", "scenarios", "sumo_net")


def _pip(*args, cwd):
    proc = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True, cwd=cwd, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.slow
def test_the_installed_wheel_runs_a_shipped_scenario_by_name_from_any_folder(tmp_path):
    project = tmp_path / "project"
    project.mkdir()
    for name in PROJECT_FILES:
        source = REPO / name
        if source.is_dir():  # the package's links to scenarios/ and sumo_net/ kept as links
            shutil.copytree(source, project / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        else:
            shutil.copy2(source, project / name)
    _pip("wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w", str(tmp_path / "dist"), str(project),
         cwd=tmp_path)
    (wheel,) = (tmp_path / "dist").glob("vcfusion-*.whl")
    target = tmp_path / "site"
    _pip("install", "--no-deps", "--no-index", "-q", "--target", str(target), str(wheel), cwd=tmp_path)

    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target)}

    def vcfusion(*args):
        return subprocess.run([sys.executable, "-m", "vcfusion", *args], capture_output=True, text=True, cwd=cwd,
                              env=env, timeout=300)

    where = subprocess.run([sys.executable, "-c", "import vcfusion; print(vcfusion.__file__)"], capture_output=True,
                           text=True, cwd=cwd, env=env)
    assert where.stdout.strip() == str(target / "vcfusion" / "__init__.py")  # the wheel's, not the checkout's

    run = vcfusion("run", "accident", "--seed", "0", "--out", "out/accident")
    assert run.returncode == 0, run.stderr
    folder = cwd / "out" / "accident"
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["simulated_s"] > 0 and summary["seed"] == 0
    assert sorted(p.name for p in folder.iterdir()) == summary["files"]  # complete: every file it lists
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["scenario"]["name"] == "accident"
    assert [p.name for p in cwd.iterdir()] == ["out"]  # nothing written beside --out

    listing = vcfusion("scenarios")
    assert listing.returncode == 0, listing.stderr
    assert str(target / "vcfusion" / "scenarios") in listing.stdout.splitlines()[0]
    names = [line.split()[0] for line in listing.stdout.splitlines()[1:]]
    assert names == sorted(p.relative_to(REPO / "scenarios").with_suffix("").as_posix()
                           for p in (REPO / "scenarios").rglob("*.yaml"))

    version = vcfusion("--version")
    (dist,) = metadata.distributions(name="vcfusion", path=[str(target)])
    assert version.returncode == 0 and version.stdout.strip() == f"vcfusion {dist.version}"

    build = vcfusion("build-net")  # the installed networks are not rewritten
    assert build.returncode == 2 and build.stderr.startswith("error: --net-dir: required when vcfusion is installed")
    assert [p.name for p in cwd.iterdir()] == ["out"]
