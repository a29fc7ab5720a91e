"""The layering contract of STYLE.md, checked on the source: calib imports neither drivers nor
acquire; drivers never imports acquire; no runtime module imports tests."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    "calib": {"drivers", "acquire", "tests"},
    "drivers": {"acquire", "tests"},
    "acquire": {"tests"},
}


def imported_top_levels(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and ":" in node.value:
            # "module:Class" registry strings are imports too.
            mod = node.value.split(":")[0]
            if mod.replace(".", "").replace("_", "").isalnum() and "." in mod:
                names.add(mod.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_package_never_imports_a_higher_layer(package: str) -> None:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources found under {package}/"
    offenders = {
        str(f.relative_to(ROOT)): sorted(imported_top_levels(f) & FORBIDDEN[package]) for f in files
    }
    offenders = {k: v for k, v in offenders.items() if v}
    assert not offenders, f"{package}/ imports a layer above it: {offenders}"


def test_checker_sees_a_forbidden_import(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("from acquire.cli import app\nREG = 'drivers.natnet.client:NatNetSensor'\n")
    assert imported_top_levels(bad) >= {"acquire", "drivers"}
