#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install heml-gym with
# the extras named in $HEML_EXTRAS (default: test), pinned by constraints.txt.
# Usage: source scripts/setup_env.sh   (then `python` is the venv's)
# PYTHON picks the interpreter (default python3); it must be 3.11 or newer.
# pip's and setuptools' output goes to .venv/install.log; it is shown only if the install fails.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${HEML_VENV:-$root/.venv}"
extras="${HEML_EXTRAS:-test}"
py="${PYTHON:-python3}"
if [ ! -x "$venv/bin/python" ]; then
  if ! command -v "$py" > /dev/null; then
    echo "[setup] error: no '$py' on PATH: install Python 3.11 or newer, or set PYTHON=/path/to/python3.11" >&2
    return 1 2> /dev/null || exit 1
  fi
  # numpy 2.4 and scipy 1.17 (the pinned versions) need Python 3.11 or newer
  if ! "$py" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "[setup] error: heml-gym needs Python 3.11 or newer; $py is $("$py" -c 'import platform; print(platform.python_version())'): set PYTHON=/path/to/python3.11" >&2
    return 1 2> /dev/null || exit 1
  fi
  echo "[setup] creating virtual environment $venv ($("$py" -c 'import platform; print("Python", platform.python_version())'))"
  "$py" -m venv "$venv"
fi
# shellcheck disable=SC1091
source "$venv/bin/activate"
stamp="$venv/.heml-installed-$(cat "$root/constraints.txt" "$root/pyproject.toml" | cksum | cut -d' ' -f1)-${extras//,/_}"
if [ ! -f "$stamp" ]; then
  log="$venv/install.log"
  : > "$log"
  _heml_pip() {  # quiet pip: its output goes to the log, which is shown if it fails
    if ! python -m pip install --disable-pip-version-check "$@" >> "$log" 2>&1; then
      tail -n 40 "$log" >&2
      echo "[setup] error: 'pip install $*' failed; the whole log is $log" >&2
      return 1
    fi
  }
  echo "[setup] installing heml-gym[$extras], pinned by constraints.txt (a few minutes the first time; log: $log)"
  _heml_pip --upgrade pip
  case ",$extras," in
    *,train,*|*,test,*|*,all,*)
      echo "[setup]   torch 2.13.0 (the CPU build, installed first so no extra pulls the CUDA build)"
      _heml_pip torch==2.13.0 ;;
  esac
  echo "[setup]   heml-gym and its dependencies"
  _heml_pip -c "$root/constraints.txt" -e "$root[$extras]"
  touch "$stamp"
  echo "[setup] done"
fi
set +euo pipefail
