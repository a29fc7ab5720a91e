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


# calib's wings, lowest first: a wing may import only the wings before it (and itself).
# The README's "Layout" section states the same order.
CALIB_WINGS = ("io", "robot", "measure", "ik", "plan", "fit", "report")


def wings_imported(path: Path, package: str = "calib") -> set[str]:
    """The wings of ``package`` that the module at ``path`` imports (absolute imports and registry
    strings; for ``acquire``, its top-level modules too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    mods: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import (use {package}.<wing>.<module>)"
            if node.module == package:
                mods.update(f"{package}.{a.name}" for a in node.names)
            elif node.module:
                mods.add(node.module)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and ":" in node.value:
            mods.add(node.value.split(":")[0])
    return {m.split(".")[1] for m in mods if m.startswith(f"{package}.") and m.count(".") >= 1}


def wing_violations(root: Path, order: tuple[str, ...]) -> dict[str, list[str]]:
    rank = {w: i for i, w in enumerate(order)}
    bad: dict[str, list[str]] = {}
    for f in sorted(root.rglob("*.py")):
        rel = f.relative_to(root)
        if len(rel.parts) < 2:  # calib/__init__.py sits above the wings
            continue
        wing = rel.parts[0]
        if wing not in rank:
            bad[str(rel)] = [f"not in a known wing ({wing})"]
            continue
        wrong = sorted(
            w for w in wings_imported(f, root.name) if w not in rank or rank[w] > rank[wing]
        )
        if wrong:
            bad[str(rel)] = wrong
    return bad


def test_calib_wings_import_one_way() -> None:
    calib = ROOT / "calib"
    assert {p.name for p in calib.iterdir() if (p / "__init__.py").is_file()} == set(CALIB_WINGS)
    assert not [p.name for p in calib.glob("*.py") if p.name != "__init__.py"], (
        "calib/ holds only wings (and __init__.py)"
    )
    bad = wing_violations(calib, CALIB_WINGS)
    assert not bad, f"calib wing imports a wing above it (order {CALIB_WINGS}): {bad}"


def test_wing_checker_sees_a_reversed_order() -> None:
    assert wing_violations(ROOT / "calib", tuple(reversed(CALIB_WINGS)))


# acquire's wings, lowest first: a wing may import only the wings before it (and itself);
# cli.py, entry.py and __main__.py sit above them all. docs/contributing.md states the same order.
ACQUIRE_WINGS = ("plan", "record", "live", "run", "daemon", "station", "commands")


def test_acquire_wings_import_one_way() -> None:
    acquire = ROOT / "acquire"
    assert {p.name for p in acquire.iterdir() if (p / "__init__.py").is_file()} == set(ACQUIRE_WINGS)
    top = {p.name for p in acquire.glob("*.py")}
    assert top == {"__init__.py", "__main__.py", "cli.py", "entry.py"}, f"acquire/ holds only wings and its entry points: {top}"
    bad = wing_violations(acquire, ACQUIRE_WINGS)
    assert not bad, f"acquire wing imports a wing above it (order {ACQUIRE_WINGS}): {bad}"


def module_graph(package: str) -> dict[str, set[str]]:
    """Module → the modules of ``package`` it imports anywhere in its body (function-level too)."""
    root = ROOT / package
    mods = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p for p in root.rglob("*.py")}
    graph = {}
    for name, path in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                for a in node.names:
                    full = f"{node.module}.{a.name}"
                    deps.add(full if full in mods else node.module)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[name] = {d for d in deps if d in mods and d != name and not name.startswith(d + ".")}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.mark.parametrize("package", ["calib", "acquire", "drivers"])
def test_no_import_circles(package: str) -> None:
    """No module imports, even inside a function, a module that imports it back (directly or
    through others): a circle means two modules are one, or one holds what belongs to a third."""
    assert import_cycles(module_graph(package)) == []


def test_the_circle_finder_finds_a_circle() -> None:
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
