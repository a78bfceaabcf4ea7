#!/usr/bin/env bash
# Download, here (where PyPI answers), the packages a GPU machine without internet lacks for
# scripts/gpu_check.sh, into .whl/ (ignored by git; carry it to the device machine).
#
#   bash scripts/gpu_wheels.sh          # about 7 MB
#
# The GPU machine has Python 3.12 with a CUDA torch, NumPy 2, numba, SciPy, transformers,
# rich, jaxtyping and ninja. It lacks gsplat (a pure-Python wheel whose CUDA kernels compile
# there on first use), plyfile and pykdtree, and pycut-pursuit, whose 0.1.4 wheels for 3.12 are
# built against NumPy 1: its 0.1.3 source is carried and built there against NumPy 2.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dest=$root/.whl
python=${THGS_PYTHON:-$root/.venv/bin/python}
mkdir -p "$dest"
platforms=()
for tag in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64; do
  platforms+=(--platform "$tag")
done
"$python" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
  --implementation cp "${platforms[@]}" -d "$dest" \
  gsplat==1.5.3 plyfile==1.1.3 pykdtree==1.4.3
"$python" -m pip download -q --no-deps --no-binary=:all: -d "$dest" pycut-pursuit==0.1.3
du -sh "$dest"
