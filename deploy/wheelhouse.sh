#!/usr/bin/env bash
# Fill a wheelhouse for an offline image build: the CPU build of torch, every runtime
# dependency of pitune at the versions of deploy/constraints.txt, and the build
# requirements (setuptools, wheel), as wheels for CPython 3.11 on Linux x86_64 (the
# image's Python), whatever Python runs this script. Run it where PyPI and the PyTorch
# CPU index are reachable (or a mirror: --index-url), carry the directory over with the
# sources, and build (docs/deploy.md, "Building the image"):
#
#   deploy/wheelhouse.sh [DIR]        # default DIR: deploy/wheelhouse (the build context)
#   deploy/wheelhouse.sh --index-url https://pypi.mirror.example/simple \
#       --torch-index-url https://download.pytorch.org/whl/cpu DIR
#
# The Dockerfile installs from deploy/wheelhouse alone when it holds wheels;
# deploy/smoke.sh --wheelhouse DIR links DIR's wheels there.
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
DEST=$ROOT/deploy/wheelhouse
INDEX=()
TORCH_INDEX=(--index-url https://download.pytorch.org/whl/cpu --extra-index-url https://pypi.org/simple)
PYTHON=${PYTHON:-python3}
while [ $# -gt 0 ]; do
  case "$1" in
    --index-url) INDEX=(--index-url "$2"); shift 2 ;;
    --torch-index-url) TORCH_INDEX=(--index-url "$2"); shift 2 ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    -*) echo "wheelhouse.sh: unknown option $1" >&2; exit 2 ;;
    *) DEST=$1; shift ;;
  esac
done
mkdir -p "$DEST"
TARGET=(--only-binary=:all: --python-version 3.11 --implementation cp --abi cp311
        --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 --platform linux_x86_64)

# torch first, from the CPU index (a plain `pip download torch` gets the CUDA build)
"$PYTHON" -m pip download --quiet --dest "$DEST" "${TARGET[@]}" --no-deps "${TORCH_INDEX[@]}" \
  torch==2.13.0
# pitune's dependencies (torch's own included), pinned by the image's constraints, and
# the build requirements of pyproject.toml
"$PYTHON" -m pip download --quiet --dest "$DEST" "${TARGET[@]}" "${INDEX[@]}" \
  --constraint "$ROOT/deploy/constraints.txt" --find-links "$DEST" \
  "$ROOT" "setuptools>=74.1" wheel
rm -f "$DEST"/pitune-*   # the project itself is built from the sources in the image
echo "wheelhouse.sh: $(find "$DEST" -name '*.whl' | wc -l) wheels, $(du -sh "$DEST" | cut -f1) in $DEST"
