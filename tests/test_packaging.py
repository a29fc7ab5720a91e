"""A built wheel holds the robot models, example plans and simulated cell; installed (not
editable) into a fresh virtual environment, `acquire run example --fake` works from any folder.

Builds the wheel from a copy of the source tree (the checkout is left untouched) without
build isolation when setuptools and wheel are importable (fast, no index needed), else as
`pip` would for an integrator. The venv sees the dependencies (numpy, scipy, zenoh, …) of the
interpreter that runs pytest, wherever the README's install put them — the system Python, a
venv, or a ``--user`` install: a ``.pth`` file in the new venv lists that interpreter's site
folders (``dependency_paths``), never the checkout or an editable install. The test checks that
`acquire`, `calib` and `drivers` are imported from the venv's own copy.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# One xdist worker runs them all (./test --dist loadgroup): the wheel and venv are built once.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(420), pytest.mark.xdist_group("packaging")]

IGNORE = shutil.ignore_patterns(".git", "runs", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                                ".hypothesis", "tests", ".helpers")


def clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(extra)
    return env


def run(cmd: list, cwd: Path, timeout: float, env: dict | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env or clean_env(), capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"{cmd} exited {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def dependency_paths() -> list[str]:
    """The folders the running interpreter imports its dependencies from: its site folders
    (``site.getsitepackages()``, the user site) and any other ``sys.path`` folder that is not
    the standard library, not in this checkout and holds no copy of this project (another
    checkout, an editable install's source folder). Non-folders (an editable install's path hook, zip files) are left out."""
    import site
    import sysconfig

    stdlib = {Path(sysconfig.get_path(k)).resolve() for k in ("stdlib", "platstdlib")}
    candidates = list(site.getsitepackages())
    if site.ENABLE_USER_SITE or os.path.isdir(site.getusersitepackages()):
        candidates.append(site.getusersitepackages())
    candidates += sys.path
    out: list[str] = []
    for entry in candidates:
        path = Path(entry or ".").resolve()
        if not path.is_dir() or path in stdlib or path.name == "lib-dynload" or path.is_relative_to(ROOT):
            continue  # (the checkout and its test folders, which pytest puts on sys.path)
        if any((path / pkg / "__init__.py").is_file() for pkg in ("acquire", "calib", "drivers")):
            continue  # a checkout of this project: the venv must use its own installed copy
        if str(path) not in out:
            out.append(str(path))
    return out


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    """Build the wheel, make a venv, pip install the wheel into it; return their paths."""
    base = tmp_path_factory.mktemp("packaging")
    src = base / "src"
    shutil.copytree(ROOT, src, symlinks=True, ignore=IGNORE)
    dist = base / "dist"
    isolated = importlib.util.find_spec("wheel") is None or importlib.util.find_spec("setuptools") is None
    build = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", dist, "./src"]
    if not isolated:
        build[4:4] = ["--no-build-isolation", "--no-index"]
    run(build, base, 240)
    (wheel,) = dist.glob("remaster-*.whl")
    venv = base / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", venv], base, 120)
    python = venv / "bin" / "python"
    # The running interpreter's dependencies, after the venv's own site-packages (a .pth line
    # appends a folder to sys.path; .pth files inside it, e.g. an editable install's finder,
    # are not run).
    purelib = run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], base, 60).stdout.strip()
    Path(purelib, "remaster-test-deps.pth").write_text("".join(f"{p}\n" for p in dependency_paths()))
    # pip comes from those folders too; --ignore-installed: an editable remaster there must not
    # make pip skip the install.
    run([python, "-m", "pip", "install", "--no-deps", "--ignore-installed", "--no-index", "-q", wheel], base, 180)
    work = base / "elsewhere"  # any folder: no checkout, no plan, nothing beside it
    work.mkdir()
    return {"wheel": wheel, "venv": venv, "python": python, "acquire": venv / "bin" / "acquire", "work": work}


def test_the_wheel_holds_models_plans_and_the_simulated_cell(installed):
    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    for robot in ROOT.glob("fixtures/robots/*.yaml"):
        assert f"calib/data/robots/{robot.name}" in names
    for plan in ROOT.glob("fixtures/plans/*.yaml"):
        assert f"calib/data/plans/{plan.name}" in names
    assert "calib/data/sim/default.yaml" in names
    assert "calib/data/foxglove/remaster-layout.json" in names
    for shipped in ROOT.glob("drivers/kuka_rsi/controller/*"):  # what a KR C4 needs, RSI context included
        assert f"drivers/kuka_rsi/controller/{shipped.name}" in names
    assert not any(n.startswith("fixtures/") for n in names)  # no stray top-level package


def test_the_installed_package_finds_its_data_outside_a_checkout(installed):
    probe = (
        "import json, acquire, calib, drivers\n"
        "from calib.io import resources\n"
        "from drivers.sim.config import DEFAULT_CONFIG_PATH, load_sim_config\n"
        "cfg = load_sim_config(DEFAULT_CONFIG_PATH)\n"
        "print(json.dumps({'modules': [acquire.__file__, calib.__file__, drivers.__file__],\n"
        "  'sim': str(DEFAULT_CONFIG_PATH), 'sim_exists': DEFAULT_CONFIG_PATH.is_file(), 'robot': str(cfg.robot),\n"
        "  'plans': [p.name for p in resources.packaged('plans')]}))\n"
    )
    out = json.loads(run([installed["python"], "-c", probe], installed["work"], 60).stdout)
    venv = str(installed["venv"].resolve())
    for module in out["modules"]:
        assert Path(module).resolve().as_posix().startswith(venv), module
    assert out["sim_exists"] and out["sim"].startswith(venv), out["sim"]
    assert Path(out["robot"]).is_file() and out["robot"].startswith(venv)
    assert out["plans"] == sorted(p.name for p in ROOT.glob("fixtures/plans/*.yaml"))
    listing = run([installed["acquire"], "examples"], installed["work"], 60).stdout
    assert f"{venv}/" in listing and "example" in listing and "kuka_iiwa14_r820" in listing
    layout = next(line.strip() for line in listing.splitlines() if line.strip().endswith("remaster-layout.json"))
    assert layout.startswith(venv) and Path(layout).is_file(), listing  # the installed copy, not a checkout's


def test_acquire_run_example_fake_from_any_folder_writes_its_result_there(installed):
    work = installed["work"]
    proc = subprocess.run([str(installed["acquire"]), "run", "example", "--fake"], cwd=work, env=clean_env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (result,) = (work / "runs").glob("example-*/result.json")
    doc = json.loads(result.read_text())
    assert len(doc["joint_offsets"]) == 7
    assert (result.parent / "report.html").is_file()
    assert not list(installed["venv"].rglob("*.mcap"))  # nothing written into the installed package
    assert ": finished" in proc.stdout
