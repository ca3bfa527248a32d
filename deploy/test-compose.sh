#!/usr/bin/env bash
# The Compose farm, tested on the real engine (.ci/run runs this):
#   1. build the image;
#   2. start the farm with 3 workers;
#   3. render the Cornell box through it, from the host over the published
#      port (`forward`: rays cross between the containers) and with the
#      one-shot submit service (`adaptive`), and compare both images bit for
#      bit with the single-machine render;
#   4. tear the farm down (also on failure).
# It never skips: without a Docker engine and Compose it fails, saying so.
# LOCUS_BIN=path uses that binary for the image (see docker/build-image.sh);
# the host side uses target/release/locus.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/.." && pwd)"
cd "$root"

fail() { echo "test-compose: FAILED: $*" >&2; exit 1; }

if docker compose version >/dev/null 2>&1; then
    compose=(docker compose)
elif command -v docker-compose >/dev/null 2>&1; then
    compose=(docker-compose)
else
    fail "neither 'docker compose' nor 'docker-compose' is installed"
fi
docker info >/dev/null 2>&1 || fail "no Docker engine answers (docker info failed)"

# Built (or found up to date) every time: a stale host binary would be
# compared with a fresh image.
cargo build --release --locked -p locus
locus="$root/target/release/locus"

work="$(mktemp -d)"
project="locus-test-$$"
tag="locus:test-$$"
export LOCUS_IMAGE="$tag" LOCUS_WORKER_THREADS=1 LOCUS_WORKER_BUDGET=1G
export LOCUS_TOKEN_FILE_HOST="$work/secrets/token" LOCUS_OUT="$work/out"
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
export LOCUS_PORT="$(free_port)" LOCUS_HTTP_PORT="$(free_port)"
dc() { "${compose[@]}" -p "$project" -f "$here/docker-compose.yml" "$@"; }
cleanup() {
    status=$?
    if [[ $status -ne 0 ]]; then
        echo "--- farm logs ---" >&2
        dc logs --no-color --tail 40 >&2 || true
    fi
    dc --profile submit down -v --remove-orphans >/dev/null 2>&1 || true
    docker image rm -f "$tag" >/dev/null 2>&1 || true
    rm -rf "$work"
    exit $status
}
trap cleanup EXIT

echo "== 1. image" >&2
"$here/docker/build-image.sh" "$tag" >/dev/null
docker image inspect "$tag" --format 'image {{.Id}}: {{.Size}} bytes' >&2

mkdir -p "$work/secrets" "$work/out"
head -c 24 /dev/urandom | od -An -tx1 | tr -d ' \n' >"$LOCUS_TOKEN_FILE_HOST"
chmod 644 "$LOCUS_TOKEN_FILE_HOST"
chmod 777 "$work/out"

echo "== 2. farm: scheduler and 3 workers" >&2
dc up -d --scale worker=3 scheduler worker
deadline=$((SECONDS + 60))
until [[ "$(dc logs --no-color scheduler 2>/dev/null | grep -c 'worker registered')" -ge 3 ]]; do
    ((SECONDS < deadline)) || fail "3 workers did not register within 60 s"
    sleep 1
done

echo "== 3. render: one machine, then the farm twice" >&2
scene=scenes/cornell-box/cornell.toml
opts=(--spp 16)
"$locus" render "$scene" "${opts[@]}" -o "$work/single.exr" >/dev/null
timeout 300 "$locus" submit --scheduler "127.0.0.1:$LOCUS_PORT" --token-file "$LOCUS_TOKEN_FILE_HOST" \
    "$scene" "${opts[@]}" --workers 3 --fetch forward -o "$work/host.exr" >/dev/null ||
    fail "submit from the host failed"
forwarded="$(python3 -c 'import json,sys; w=json.load(open(sys.argv[1]))["farm"]["workers"]; print(sum(x["stats"]["forwarded_out"] for x in w))' "$work/host.json")"
((forwarded > 0)) || fail "no ray crossed between the worker containers"
timeout 300 env LOCUS_UID="$(id -u)" LOCUS_GID="$(id -g)" "${compose[@]}" -p "$project" \
    -f "$here/docker-compose.yml" run --rm submit \
    "/$scene" "${opts[@]}" --workers 3 --fetch adaptive -o /out/oneshot.exr >/dev/null ||
    fail "the one-shot submit service failed"
"$locus" diff --exact "$work/host.exr" "$work/single.exr" || fail "host submit differs from one machine"
"$locus" diff --exact "$work/out/oneshot.exr" "$work/single.exr" ||
    fail "one-shot submit differs from one machine"
# The status address, published like the scheduler's: what it counted.
"$locus" status --http "127.0.0.1:$LOCUS_HTTP_PORT" >&2 || fail "locus status failed"
curl -fsS "http://127.0.0.1:$LOCUS_HTTP_PORT/metrics" >"$work/metrics" || fail "no /metrics"
grep -E '^locus_(tiles_total|jobs_total|forwarded_queries_total|worker_up)' "$work/metrics" >&2
grep -q '^locus_jobs_total{outcome="done"} 2$' "$work/metrics" || fail "/metrics does not count 2 jobs done"
echo "test-compose: ok: 3 worker containers, $forwarded rays forwarded between them, both farm images bit-identical to one machine" >&2

echo "== 4. down" >&2
