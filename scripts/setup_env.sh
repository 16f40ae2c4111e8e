#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install heml-gym with
# the extras named in $HEML_EXTRAS (default: test), pinned by constraints.txt.
# Usage: source scripts/setup_env.sh   (then `python` is the venv's)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${HEML_VENV:-$root/.venv}"
extras="${HEML_EXTRAS:-test}"
py="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment $venv"
  "$py" -m venv "$venv"
fi
# shellcheck disable=SC1091
source "$venv/bin/activate"
stamp="$venv/.heml-installed-$(cat "$root/constraints.txt" "$root/pyproject.toml" | cksum | cut -d' ' -f1)-${extras//,/_}"
if [ ! -f "$stamp" ]; then
  echo "[setup] installing heml-gym[$extras] (pinned by constraints.txt)"
  python -m pip install --quiet --upgrade pip
  case ",$extras," in
    *,train,*|*,test,*|*,all,*) python -m pip install --quiet torch==2.13.0 ;;  # CPU build, first
  esac
  python -m pip install --quiet -c "$root/constraints.txt" -e "$root[$extras]"
  touch "$stamp"
fi
set +euo pipefail
