# Sourced by ./demo and ./test (POSIX sh): install the project with its test tools, once.
#
# Installs with `$PY -m pip install -e ".[test]"` (PY: $PYTHON or python3 — a venv's python,
# the system one, or with PIP_USER=1 a user install) only when this interpreter does not already
# import `acquire` from this checkout with every dependency of the `test` extra installed; so
# running either script again installs nothing.
PY=${PYTHON:-python3}

installed() {
    # -P: the current folder is not on sys.path, so `acquire` must come from the install
    "$PY" -P - "$(pwd)" <<'PYEOF' >/dev/null 2>&1
import importlib.metadata as md, pathlib, re, sys
import acquire
assert pathlib.Path(acquire.__file__).resolve().parents[1] == pathlib.Path(sys.argv[1]).resolve()
for req in md.distribution("remaster").requires or []:
    if "extra ==" in req and not re.search(r"extra == .test.", req):
        continue
    md.version(re.split(r"[ ;<>=!~\[(]", req, maxsplit=1)[0])  # PackageNotFoundError if missing
PYEOF
}

ensure_installed() {
    if ! installed; then
        echo "== installing: $PY -m pip install -e \".[test]\""
        "$PY" -m pip install -e ".[test]"
    fi
}
