#!/usr/bin/env bash
# Build thgs's sdist and wheel, install the wheel with plain pip into a fresh virtual environment
# and run `thgs demo` there: what `pip install 'thgs[demo]'` gives a user.
#
#   bash scripts/check_package.sh          # after scripts/setup.sh (uses .venv to build)
#
# The wheel is built from the sdist (python -m build), so both are checked. The fresh environment
# gets torch==2.13.0 first and scripts/constraints.txt after, as scripts/setup.sh does, and only
# wheels (--only-binary :all:): nothing is compiled. pip does not byte-compile what it installs
# (--no-compile: torch alone installs in 5 s instead of 19 s): the one process that runs there
# compiles what it imports, the same files either way. The built files stay in dist/.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${THGS_VENV:-$root/.venv}
python=${THGS_PYTHON:-python3}
constraints=$root/scripts/constraints.txt
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
start=$SECONDS

echo "package: building the sdist and, from it, the wheel"
rm -rf "$root/dist"
"$venv/bin/python" -m build --outdir "$root/dist" "$root" >"$work/build.log" 2>&1 \
  || { cat "$work/build.log" >&2; exit 1; }
wheel=$(ls "$root"/dist/thgs-*.whl)
ls "$root"/dist/thgs-*.tar.gz >/dev/null
echo "package: built in $((SECONDS - start)) s"

echo "package: installing $(basename "$wheel")[demo] into a fresh virtual environment"
"$python" -m venv "$work/venv"
pip=("$work/venv/bin/python" -m pip --disable-pip-version-check --quiet)
"${pip[@]}" install --no-compile torch==2.13.0
"${pip[@]}" install --no-compile --only-binary :all: -c "$constraints" "$wheel[demo]"
"${pip[@]}" check
if "$work/venv/bin/python" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('torchvision') is None)"; then
  echo "package: torchvision got installed; it breaks transformers with the CPU torch" >&2
  exit 1
fi
echo "package: installed in $((SECONDS - start)) s"

echo "package: thgs demo in the fresh environment"
cd "$work"
"$work/venv/bin/thgs" demo --out "$work/demo" --cache "$work/cache"
for file in field.thgs report.md report.json; do
  [[ -s $work/demo/$file ]] || { echo "package: the demo wrote no $file" >&2; exit 1; }
done
echo "package: done in $((SECONDS - start)) s"
