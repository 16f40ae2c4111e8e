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
# one worker per core, at most 4 (each holds its own compiled kernels, about 1.5 GB)
workers="${HEML_TEST_WORKERS:-$(python -c 'import os; print(min(len(os.sched_getaffinity(0)), 4))')}"
python -m pytest -q -n "$workers" --dist loadgroup "$@"
