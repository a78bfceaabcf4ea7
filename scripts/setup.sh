#!/usr/bin/env bash
# Set up a virtual environment for thgs on a fresh machine.
#
#   bash scripts/setup.sh            # creates .venv (or $THGS_VENV) with every extra
#   THGS_EXTRAS=dev bash scripts/setup.sh
#
# Steps: create the venv; install torch==2.13.0 first; pin it with scripts/constraints.txt in every
# later pip call; install thgs (editable) with its extras, all from wheels (pycut-pursuit's wheel and
# the NumPy it was built against come from pyproject.toml), byte-compiled: the tests start many
# processes, and where PYTHONDONTWRITEBYTECODE is set (as on this project's machines) nothing
# imported is ever cached otherwise. torchvision is never installed, and the script fails if
# anything pulled it in. Idempotent: a second run with unchanged inputs does nothing.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${THGS_VENV:-$root/.venv}
python=${THGS_PYTHON:-python3}
constraints=$root/scripts/constraints.txt
# gsplat ([gpu]) is a pure-Python wheel that compiles its CUDA kernels on first use on a GPU; on a
# CPU machine it is installed too, for the tests against its pure-torch projection.
extras=${THGS_EXTRAS:-models,viewer,gpu,demo,bench,cluster,dev}

# The browser test (tests/test_viewer_browser.py) drives Debian's Chromium through Playwright.
# Install it where apt can (as root, or with password-less sudo); THGS_CHROMIUM=0 skips this.
# Without it, that one test is skipped and says why.
if [[ ${THGS_CHROMIUM:-1} != 0 && ! -x /usr/bin/chromium ]] && command -v apt-get >/dev/null; then
  if [[ $(id -u) == 0 ]]; then
    apt=(env DEBIAN_FRONTEND=noninteractive apt-get -y -q)
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then
    apt=(sudo -n env DEBIAN_FRONTEND=noninteractive apt-get -y -q)
  else
    apt=()
  fi
  echo "setup: Chromium for the browser test (apt: chromium, chromium-driver)"
  if [[ ${#apt[@]} == 0 ]] \
     || ! { "${apt[@]}" install chromium chromium-driver >/dev/null 2>&1 \
            || { "${apt[@]}" update >/dev/null 2>&1 \
                 && "${apt[@]}" install chromium chromium-driver >/dev/null 2>&1; }; }; then
    echo "setup: could not install Chromium (needs root or sudo); the browser test will be skipped"
  fi
fi

stamp=$venv/.thgs-setup
inputs=$(cat "$root/pyproject.toml" "$constraints" "$root/scripts/setup.sh"; echo "extras=$extras")
digest=$(printf '%s' "$inputs" | sha256sum | cut -d' ' -f1)
if [[ -x $venv/bin/python && -f $stamp && $(cat "$stamp") == "$digest" ]]; then
  echo "setup: $venv is up to date"
  exit 0
fi

start=$SECONDS
if [[ ! -x $venv/bin/python ]]; then
  echo "setup: creating $venv"
  "$python" -m venv "$venv"
fi
pip=("$venv/bin/python" -m pip --disable-pip-version-check)

echo "setup: torch 2.13.0 (CPU build)"
"${pip[@]}" install --quiet torch==2.13.0
echo "setup: thgs[$extras]"
"${pip[@]}" install --quiet -c "$constraints" -e "$root[$extras]"

if "$venv/bin/python" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('torchvision') is None)"; then
  echo "setup: torchvision got installed; it breaks transformers with the CPU torch. Remove what pulled it in." >&2
  exit 1
fi
"${pip[@]}" check
echo "$digest" > "$stamp"
echo "setup: done in $((SECONDS - start)) s"
