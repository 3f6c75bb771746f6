#!/usr/bin/env bash
# A local stand-in for the python:3.11-slim-bookworm base image, for hosts that cannot pull
# from a registry (air-gapped plants, these CI machines): a Debian bookworm minbase made
# with debootstrap from a Debian mirror (or an apt proxy/local mirror), imported into the
# container engine. Needs root, debootstrap, and docker or podman.
#
#   sudo deploy/base-image.sh                  # -> pitune-base:bookworm, pitune-base:bookworm-build
#   sudo deploy/base-image.sh --mirror http://deb.debian.org/debian --engine podman
#
# Two images, both with Debian's python3 (3.11 in bookworm, like the official image):
#   pitune-base:bookworm        python3, venv, CA certificates: the runtime stage
#   pitune-base:bookworm-build  the same plus gcc and the Python headers: the build stage
# Then: deploy/smoke.sh --base pitune-base:bookworm   (or by hand:
#   docker build --build-arg PYTHON_IMAGE=pitune-base:bookworm \
#                --build-arg BUILD_IMAGE=pitune-base:bookworm-build -t pitune:local .)
set -euo pipefail

MIRROR=http://deb.debian.org/debian
ENGINE=
TAG=pitune-base:bookworm
while [ $# -gt 0 ]; do
  case "$1" in
    --mirror) MIRROR=$2; shift 2 ;;
    --engine) ENGINE=$2; shift 2 ;;
    --tag) TAG=$2; shift 2 ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "base-image.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
if [ -z "$ENGINE" ]; then
  if command -v podman >/dev/null; then ENGINE=podman; else ENGINE=docker; fi
fi
[ "$(id -u)" = 0 ] || { echo "base-image.sh: debootstrap needs root" >&2; exit 2; }
command -v debootstrap >/dev/null || {
  echo "base-image.sh: install debootstrap (apt-get install debootstrap)" >&2; exit 2; }

WORK=$(mktemp -d /var/tmp/pitune-base.XXXXXX)
trap 'rm -rf "$WORK"' EXIT
RUNTIME="python3,python3-venv,ca-certificates"
BUILD="$RUNTIME,gcc,libc6-dev,python3-dev"

make_image() {  # make_image PACKAGES TAG
  local root="$WORK/root"
  rm -rf "$root"
  echo "base-image.sh: debootstrap bookworm ($1) from $MIRROR" >&2
  debootstrap --variant=minbase --include="$1" bookworm "$root" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 || {
    tail -20 "$WORK/debootstrap.log" >&2; exit 1; }
  # `python` as in the official image (its scripts and the Dockerfile call it)
  ln -sf python3 "$root/usr/bin/python"
  # slim like the official image: no apt lists, docs or man pages
  rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/usr/share/doc/* \
    "$root"/usr/share/man/* "$root"/usr/share/info/*
  tar -C "$root" -c . | "$ENGINE" import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' - "$2" >/dev/null
  echo "base-image.sh: $2 ($("$ENGINE" image inspect --format '{{.Size}}' "$2") bytes)" >&2
}

make_image "$RUNTIME" "$TAG"
make_image "$BUILD" "$TAG-build"
