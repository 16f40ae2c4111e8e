#!/usr/bin/env bash
# Run the test suite in the project's virtual environment (created on first use), in
# parallel over the machine's cores (pytest-xdist; tests that start Ray clusters share one
# worker). Extra arguments go to pytest, e.g. `bash scripts/test.sh tests/test_envs.py -n 0`.
set -euo pipefail
cd "$(dirname "$0")/.."
HEML_EXTRAS="${HEML_EXTRAS:-test}" source scripts/setup_env.sh
set -euo pipefail
# idle OpenMP workers sleep rather than spin: two test processes share the cores
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
python -m pytest -q -n "${HEML_TEST_WORKERS:-auto}" --dist loadgroup "$@"
