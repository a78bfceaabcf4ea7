#!/usr/bin/env bash
# The GPU check in one device call: the carried wheels installed, gsplat's kernels built, the
# CUDA tests run and the GPU measured (scripts/gpu_check.py); one JSON report.
#
#   bash scripts/gpu_wheels.sh                # here, once: what the GPU machine lacks, into .whl/
#   bash scripts/gpu_check.sh                 # there (carry .whl): $OUT/gpu_check.json
#   bash scripts/gpu_check.sh --tiny --out D  # the CPU dry run at toy sizes (the tests run it)
#
# --budget-s S (default 520) is the time the whole script may take: the measurements skip the
# steps that would not finish in what the set-up leaves. thgs is imported from src/; the wheels
# in .whl/ are installed into a folder of their own (THGS_SITE, default /tmp/thgs-site), except
# in the dry run, which uses the environment it is started in (THGS_PYTHON, default python3).
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out=${OUT:-$root/gpu-check-out}
budget=520
tiny=()
while [[ $# -gt 0 ]]; do
  case $1 in
    --tiny) tiny=(--tiny) ;;
    --out) out=$2; shift ;;
    --budget-s) budget=$2; shift ;;
    *) echo "gpu_check.sh: unknown argument $1 (--tiny, --out DIR, --budget-s S)" >&2; exit 2 ;;
  esac
  shift
done
python=${THGS_PYTHON:-python3}
mkdir -p "$out"
log=$out/setup.log
: >"$log"
site_packages=
install() {
  "$python" -m pip install -q --no-index --no-deps --no-cache-dir --target "$site_packages" "$@" \
    >>"$log" 2>&1 || { echo "gpu_check.sh: pip install $* failed:" >&2; tail -20 "$log" >&2; exit 1; }
}
if [[ -d $root/.whl && ${#tiny[@]} == 0 ]]; then
  site_packages=${THGS_SITE:-/tmp/thgs-site}
  echo "installing the carried wheels into $site_packages" | tee -a "$log"
  install --no-compile --upgrade "$root"/.whl/*.whl
  # setuptools compiles an sdist's extensions one at a time unless its build_ext is told
  # otherwise: pycut-pursuit's four take 3 minutes in a row on one core
  parallel=$(mktemp)
  printf '[build_ext]\nparallel = %s\n' "$(nproc)" >"$parallel"
  for sdist in "$root"/.whl/*.tar.gz; do
    [[ -e $sdist ]] || continue
    echo "building $(basename "$sdist") against this NumPy" | tee -a "$log"
    DIST_EXTRA_CONFIG=$parallel install --no-build-isolation "$sdist"
  done
fi
export PYTHONPATH=${site_packages:+$site_packages:}$root/src${PYTHONPATH:+:$PYTHONPATH}
# gsplat compiles its kernels on first use: every core, for this GPU's architecture only
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
if [[ -z ${TORCH_CUDA_ARCH_LIST:-} ]] && command -v nvidia-smi >/dev/null; then
  TORCH_CUDA_ARCH_LIST=$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader | head -1)
  export TORCH_CUDA_ARCH_LIST
fi
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/thgs-torch-extensions}
export PYTHONUNBUFFERED=1
left=$((budget - SECONDS))
echo "set-up: ${SECONDS} s; measuring for at most ${left} s" | tee -a "$log"
exec "$python" "$root/scripts/gpu_check.py" "${tiny[@]}" --out "$out/gpu_check.json" \
  --deadline-s "$left" --setup-s "$SECONDS"
