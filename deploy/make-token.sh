#!/usr/bin/env bash
# Writes a random cluster token to deploy/secrets/token, unless one is
# there: the Compose farm reads it as a secret, and clients pass it with
# --token-file. The folder is private to you; the file itself is readable
# because Compose (outside swarm) bind-mounts it as is, and the daemons run
# as "nobody" inside their containers.
set -euo pipefail
dir="$(cd "$(dirname "$0")" && pwd)/secrets"
mkdir -p "$dir"
chmod 700 "$dir"
if [[ ! -s "$dir/token" ]]; then
    head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' >"$dir/token"
    echo >>"$dir/token"
fi
chmod 644 "$dir/token"
echo "$dir/token"
