#!/usr/bin/env bash
# Run the test suite in the project's virtual environment (created on first use).
set -euo pipefail
cd "$(dirname "$0")/.."
HEML_EXTRAS="${HEML_EXTRAS:-test}" source scripts/setup_env.sh
set -euo pipefail
python -m pytest -q "$@"
