#!/usr/bin/env bash
# A private directory of Zenoh secrets for the compose deployment, with fresh random
# passwords: credentials.txt (the router's user:password lines) and tuner.json5 and
# gateway.json5 (the clients' configs), made from the examples in deploy/zenoh/ with
# each "<user>-change-me" replaced. Point PITUNE_ZENOH_SECRETS at it (docs/deploy.md).
# Each GATEWAY_ID given also gets its own user, "gateway-<id>" (docs/deploy.md, One user
# per gateway): its line in credentials.txt and its client config gateway-<id>.json5
# (gateway.json5 as that user). The router's ACL must grant that user first, or it would
# log in and be allowed nothing: the script refuses an id that either router config
# (deploy/zenoh/router.json5, and router-tls.json5 for a TLS site) does not name.
#
#   deploy/secrets.sh /srv/pitune/zenoh [GATEWAY_ID ...]
#
# The directory is created mode 700 (it must not exist yet, or be empty); the files are
# 644, for the containers' user (uid 10001) to read through it. Exit 1 with a reason,
# before anything is written.
set -euo pipefail
die() { echo "secrets.sh: $*" >&2; exit 1; }
[ $# -ge 1 ] || die "usage: deploy/secrets.sh DIR [GATEWAY_ID ...]"
DIR=$1
shift
DEPLOY=$(cd "$(dirname "$0")" && pwd)
ACLS=("$DEPLOY/zenoh/router.json5" "$DEPLOY/zenoh/router-tls.json5")
# A gateway id: service/wire/protocol.py's LOOP_ID_PATTERN (a test keeps them equal).
ID_PATTERN='^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$'
seen=" "
for id in "$@"; do
  [[ $id =~ $ID_PATTERN ]] ||
    die "'$id' is not a gateway id (1-64 letters, digits, '_', '.', '-', the first a letter or digit)"
  case $seen in *" $id "*) die "gateway '$id' is given twice" ;; esac
  seen="$seen$id "
  for acl in "${ACLS[@]}"; do
    # what the router reads: a user named only in a // comment (a line commented out,
    # a note after one) is granted nothing
    grep -qF "usernames: [\"gateway-$id\"]" <(sed 's|//.*||' "$acl") ||
      die "the router's ACL ($acl) has no user gateway-$id: copy the gw-1 rules, subject" \
        "and policy for gateway $id into router.json5 and router-tls.json5 first" \
        "(docs/deploy.md, One user per gateway)"
  done
done
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
for id in "$@"; do
  user=gateway-$id
  pw=$(rand)
  {
    echo "// The gateway whose gateway id is \"$id\", as user $user: the router's ACL gives"
    echo "// it its own gateway's keys only (docs/deploy.md, One user per gateway), not all"
    echo "// that gateway.json5's comment below lists. Made by deploy/secrets.sh."
    sed -e "s/gateway-change-me/$pw/" -e "s/user: \"gateway\"/user: \"$user\"/" \
      "$DEPLOY/zenoh/gateway.json5"
  } >"$DIR/$user.json5"
  grep -qF "user: \"$user\", password: \"$pw\"" "$DIR/$user.json5" ||
    die "no example user and password in deploy/zenoh/gateway.json5"
  echo "$user:$pw" >>"$DIR/credentials.txt"
done
chmod 644 "$DIR"/*
echo "Zenoh secrets in $DIR: set PITUNE_ZENOH_SECRETS=$DIR in deploy/.env"
