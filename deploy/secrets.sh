#!/usr/bin/env bash
# A private directory of Zenoh secrets for the compose deployment, with fresh random
# passwords: credentials.txt (the router's user:password lines) and tuner.json5 and
# gateway.json5 (the clients' configs), made from the examples in deploy/zenoh/ with
# each "<user>-change-me" replaced. Point PITUNE_ZENOH_SECRETS at it (docs/deploy.md).
#
#   deploy/secrets.sh /srv/pitune/zenoh
#
# The directory is created mode 700 (it must not exist yet, or be empty); the files are
# 644, for the containers' user (uid 10001) to read through it. Exit 1 with a reason.
set -euo pipefail
die() { echo "secrets.sh: $*" >&2; exit 1; }
[ $# -eq 1 ] || die "usage: deploy/secrets.sh DIR"
DIR=$1
DEPLOY=$(cd "$(dirname "$0")" && pwd)
if [ -e "$DIR" ] && [ -n "$(ls -A "$DIR")" ]; then
  die "$DIR is not empty: its passwords would be replaced (remove it first)"
fi
install -d -m 700 "$DIR"
rand() { od -An -N16 -tx1 /dev/urandom | tr -d ' \n'; }
: >"$DIR/credentials.txt"
for user in tuner gateway; do
  pw=$(rand)
  sed "s/$user-change-me/$pw/" "$DEPLOY/zenoh/$user.json5" >"$DIR/$user.json5"
  grep -q "$pw" "$DIR/$user.json5" || die "no example password in deploy/zenoh/$user.json5"
  echo "$user:$pw" >>"$DIR/credentials.txt"
done
chmod 644 "$DIR"/*
echo "Zenoh secrets in $DIR: set PITUNE_ZENOH_SECRETS=$DIR in deploy/.env"
