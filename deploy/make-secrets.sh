#!/usr/bin/env bash
# Writes the farm's secrets into deploy/secrets/, keeping any already there:
#   token     a random cluster token (clients pass it with --token-file);
#   cert.pem  the farm's TLS certificate (self-signed, for the name
#   key.pem   "locus") and its key: `locus tls-init`, run from the host's
#             `locus` when there is one, else from the image.
# The Compose farm reads all three as secrets. The folder is private to
# you; the files themselves are readable because Compose (outside swarm)
# bind-mounts them as they are, and the daemons run as "nobody" inside
# their containers.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
dir="$root/deploy/secrets"
mkdir -p "$dir"
chmod 700 "$dir"
if [[ ! -s "$dir/token" ]]; then
    head -c 32 /dev/urandom | od -An -tx1 | tr -d ' \n' >"$dir/token"
    echo >>"$dir/token"
fi
if [[ ! -s "$dir/cert.pem" || ! -s "$dir/key.pem" ]]; then
    if command -v locus >/dev/null; then
        locus tls-init --force -o "$dir" >/dev/null
    elif [[ -x "$root/target/release/locus" ]]; then
        "$root/target/release/locus" tls-init --force -o "$dir" >/dev/null
    else
        docker run --rm --user "$(id -u):$(id -g)" -v "$dir:/out" \
            "${LOCUS_IMAGE:-locus:latest}" tls-init --force -o /out >/dev/null
    fi
fi
chmod 644 "$dir/token" "$dir/cert.pem" "$dir/key.pem"
echo "$dir"
