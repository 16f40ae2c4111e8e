#!/usr/bin/env bash
# The CPU matrix: the solver and env tests and a short reliability soak, with every Numba
# kernel compiled for each of several CPUs in turn, so that one machine shows what users of
# other CPUs get (rounding, and so convergence, differs between instruction sets).
#
#   bash scripts/cpu_matrix.sh                     # haswell znver3 x86-64 skylake-avx512
#   bash scripts/cpu_matrix.sh haswell x86-64      # some targets
#   CPU_MATRIX_TESTS=all bash scripts/cpu_matrix.sh   # the whole suite under each target
#   CPU_MATRIX_SOAK=0 bash scripts/cpu_matrix.sh      # skip the soak (default: 2000 env steps per env)
#
# Each target compiles into its own cache (.numba-cache/<target>/) with
# NUMBA_CPU_NAME=<target> and NUMBA_CPU_FEATURES="" (the target's own instruction set:
# NUMBA_CPU_NAME alone keeps the host's feature flags, so "haswell" on an AVX-512 host
# would still emit AVX-512). A target that needs instructions this host lacks is skipped,
# and the summary says so. Run it before you stop when you touch the physics.
set -euo pipefail
cd "$(dirname "$0")/.."
HEML_EXTRAS="${HEML_EXTRAS:-test}" source scripts/setup_env.sh
set -euo pipefail

targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(haswell znver3 x86-64 skylake-avx512)
tests="${CPU_MATRIX_TESTS:-tests/test_quasi_newton.py tests/test_model_solvers.py tests/test_simulation.py tests/test_forces.py tests/test_hessian.py tests/test_contact.py tests/test_envs.py tests/test_nothing_silent.py}"
[ "$tests" = "all" ] && tests=""
soak_steps="${CPU_MATRIX_SOAK:-2000}"
out="${CPU_MATRIX_OUT:-.numba-cache/cpu_matrix}"
mkdir -p "$out"
summary=()

for target in "${targets[@]}"; do
  missing=$(python scripts/cpu_features.py missing "$target") || { echo "unknown target $target" >&2; exit 2; }
  if [ -n "$missing" ]; then
    summary+=("$target: SKIPPED (this CPU lacks $missing)")
    echo "== $target: skipped, this CPU lacks $missing"
    continue
  fi
  echo "== $target: tests (kernels compiled for $target, cache .numba-cache/$target)"
  export NUMBA_CPU_NAME="$target" NUMBA_CPU_FEATURES="" NUMBA_CACHE_DIR="$PWD/.numba-cache/$target"
  start=$(date +%s)
  status="passed"
  # shellcheck disable=SC2086
  python -m pytest -q -p no:cacheprovider $tests || status="FAILED"
  if [ "$soak_steps" != "0" ]; then
    echo "== $target: reliability soak, $soak_steps env steps per env"
    if python benchmarks/reliability.py --steps "$soak_steps" --out "$out/$target" --no-bad-inputs; then
      soak=$(python -c "import json,sys; r=json.load(open(sys.argv[1])); s=r['soak']; print(f\"{sum(x['env_steps'] for x in s):,} env steps, \" + ', '.join(f'{k} {sum(x[k] for x in s)}' for k in ('diverged','unconverged','non_finite','exceptions')))" "$out/$target/reliability.json")
    else
      soak="soak FAILED"; status="FAILED"
    fi
  else
    soak="no soak"
  fi
  summary+=("$target: tests $status in $(( $(date +%s) - start )) s; $soak")
  unset NUMBA_CPU_NAME NUMBA_CPU_FEATURES NUMBA_CACHE_DIR
done

echo
echo "CPU matrix on $(python scripts/cpu_features.py host):"
failed=0
for line in "${summary[@]}"; do
  echo "  $line"
  case "$line" in *FAILED*) failed=1 ;; esac
done
exit $failed
