#!/usr/bin/env bash
# The main job: set up the environment (first run only) and run the demo.
set -euo pipefail
cd "$(dirname "$0")/.."
HEML_EXTRAS="${HEML_EXTRAS:-mesh}" source scripts/setup_env.sh
set -euo pipefail
python -m heml_gym.demo "$@"
