# Sourced by the set-up scripts: make .venv with the project installed (editable) and its extras.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
echo "installing blockray${1:-} into .venv (log: .venv/install.log)" >&2
if ! { .venv/bin/python -m pip install --quiet --upgrade pip &&
       .venv/bin/python -m pip install --quiet -e ".${1:-}"; } > .venv/install.log 2>&1; then
  cat .venv/install.log >&2
  echo "install failed (see above)" >&2
  exit 1
fi
export PATH="$here/.venv/bin:$PATH"
