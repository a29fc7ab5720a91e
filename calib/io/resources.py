"""The robot models, example plans, simulated cells and the Foxglove layout that ship inside
the package.

In a checkout they live in ``fixtures/{robots,plans,sim,foxglove}``; the package holds the same
folders as ``calib/data/{robots,plans,sim,foxglove}`` (symbolic links in the checkout, copies in
a built wheel),
so an installed ``remaster`` finds them with ``importlib.resources`` and needs no checkout.
The three folders keep their layout, so the relative paths inside the files
(``robot: ../robots/kuka_iiwa14_r820.yaml``) hold in both places.

``packaged("plans")`` lists the example plans, ``find("plans", "example")`` finds one by name
(``acquire run example --fake``), ``default_sim_config()`` is the simulated cell ``--fake``
and ``acquire sim`` use by default, ``is_packaged(path)`` tells whether a file is an
installed copy (a run never writes its results next to it), ``foxglove_layout()`` is the
Foxglove layout for a run log or the live view (import it in Foxglove: *Layouts → Import*).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: The kinds of packaged files and the folder of each.
KINDS = {"plans": "example measurement plans", "robots": "robot models", "sim": "simulated cells"}


def data_dir() -> Path:
    """The package's data folder (``calib/data``) as a file-system path.

    Raises RuntimeError when the package is not installed as files (e.g. imported from a zip).
    """
    root = files("calib") / "data"
    path = Path(str(root))
    if not path.is_dir():
        raise RuntimeError(f"the packaged data folder {root} is not a folder on disk; install remaster from a wheel "
                           "or a checkout (pip install .), not as a zip")
    return path


def folder(kind: str) -> Path:
    """``data_dir() / kind`` for kind in ``KINDS``; raises ValueError naming the kinds otherwise."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind of packaged file {kind!r}; allowed: {', '.join(KINDS)}")
    return data_dir() / kind


def packaged(kind: str) -> list[Path]:
    """The packaged YAML files of ``kind``, sorted by name."""
    d = folder(kind)
    return sorted(p for p in d.glob("*.yaml") if p.is_file()) if d.is_dir() else []


def find(kind: str, name: str) -> Path | None:
    """The packaged file of ``kind`` called ``name`` (with or without ``.yaml``), or None."""
    stem = name[:-5] if name.endswith(".yaml") else name
    if not stem or "/" in stem or "\\" in stem:
        return None
    path = folder(kind) / f"{stem}.yaml"
    return path if path.is_file() else None


def default_sim_config() -> Path:
    """The simulated cell ``--fake`` runs against unless a plan names another (absolute path)."""
    return (folder("sim") / "default.yaml").resolve()


#: The Foxglove layout's file name (``calib/data/foxglove/``; ``fixtures/foxglove/`` in a checkout).
FOXGLOVE_LAYOUT = "remaster-layout.json"


def foxglove_layout() -> Path:
    """The packaged Foxglove layout for a run's channels (absolute path; JSON)."""
    return (data_dir() / "foxglove" / FOXGLOVE_LAYOUT).resolve()


def foxglove_layout_hint() -> str:
    """The packaged Foxglove layout's path as text for help and listings, or why it is missing."""
    try:
        return str(foxglove_layout())
    except RuntimeError as exc:
        return f"(not found: {exc})"


def is_packaged(path: str | Path) -> bool:
    """True for a file of an installed package (under the installed ``calib`` package, links
    resolved) — not for the checkout's ``fixtures/`` the links point at."""
    package = Path(str(files("calib"))).resolve()
    try:
        Path(path).resolve().relative_to(package)
    except ValueError:
        return False
    return True


def summary(path: Path) -> str:
    """The first comment line of a packaged file (what it is), without the ``#``."""
    try:
        for line in path.read_text(encoding="utf-8").splitlines():
            if line.startswith("#"):
                text = line.lstrip("#").strip()
                return text if text.endswith((".", ":")) else text + " …"
            if line.strip():
                break
    except OSError:
        pass
    return ""
