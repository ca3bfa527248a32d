#!/usr/bin/env bash
# The Compose farm, tested on the real engine (.ci/run runs this):
#   1. build the image;
#   2. start the farm with 3 workers;
#   3. render the Cornell box through it, from the host over the published
#      port (`forward`: rays cross between the containers) and with the
#      one-shot submit service (`adaptive`), and compare both images bit for
#      bit with the single-machine render;
#   4. lose a worker mid-job twice: `docker kill` one worker container,
#      then, with it started again, cut another off the farm network
#      (`docker network disconnect`); both jobs must complete bit-identical
#      to one machine, and the cut-off worker, connected again, rejoins;
#      then kill the scheduler mid-job and start it again: the job resumes
#      from the scheduler's state volume and ends bit-identical;
#   5. tear the farm down (also on failure).
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
export LOCUS_TOKEN_FILE_HOST="$work/secrets/token" LOCUS_TLS_DIR_HOST="$work/secrets" LOCUS_OUT="$work/out"
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
"$locus" tls-init -o "$LOCUS_TLS_DIR_HOST" >/dev/null
chmod 644 "$LOCUS_TOKEN_FILE_HOST" "$LOCUS_TLS_DIR_HOST/key.pem"
# Every host client trusts the farm's certificate.
tls=(--tls-ca "$LOCUS_TLS_DIR_HOST/cert.pem")
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
# TLS is on: a client that does not speak it is turned away at once.
if timeout 60 "$locus" submit --scheduler "127.0.0.1:$LOCUS_PORT" --token-file "$LOCUS_TOKEN_FILE_HOST" \
    "$scene" "${opts[@]}" --workers 3 -o "$work/plain.exr" >/dev/null 2>&1; then
    fail "a client without TLS was served"
fi
timeout 300 "$locus" submit --scheduler "127.0.0.1:$LOCUS_PORT" --token-file "$LOCUS_TOKEN_FILE_HOST" "${tls[@]}" \
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
grep -E '^locus_(tile_passes_total|jobs_total|forwarded_queries_total|worker_up)' "$work/metrics" >&2
grep -q '^locus_jobs_total{outcome="done"} 2$' "$work/metrics" || fail "/metrics does not count 2 jobs done"
echo "test-compose: ok: 3 worker containers over TLS (a plain client refused), $forwarded rays forwarded between them, both farm images bit-identical to one machine" >&2

echo "== 4. a worker lost mid-job: killed, then cut off the network" >&2
status_json() { curl -fsS "http://127.0.0.1:$LOCUS_HTTP_PORT/status"; }
# Waits until the running job has tile passes in (at least $1, default 1): the
# loss then lands mid-render.
wait_rendering() {
    local deadline=$((SECONDS + 120))
    until status_json | python3 -c 'import json,sys; r=json.load(sys.stdin)["running"]; sys.exit(0 if r and r["tile_passes_done"] >= int(sys.argv[1]) else 1)' "${1:-1}" 2>/dev/null; do
        ((SECONDS < deadline)) || fail "the job did not start rendering within 120 s"
        sleep 0.2
    done
}
registered() { status_json | python3 -c 'import json,sys; print(len(json.load(sys.stdin)["workers"]))'; }
# Waits up to 60 s until 3 workers are registered; $1 says who failed to.
wait_registered() {
    local deadline=$((SECONDS + 60))
    until [[ "$(registered 2>/dev/null)" -ge 3 ]]; do
        ((SECONDS < deadline)) || fail "$1 within 60 s"
        sleep 0.5
    done
}
# Submits the long job from the host in the background, writing $1.exr.
submit_long() {
    timeout 300 "$locus" submit --scheduler "127.0.0.1:$LOCUS_PORT" --token-file "$LOCUS_TOKEN_FILE_HOST" "${tls[@]}" \
        "$scene" "${long[@]}" --workers 3 --fetch forward -o "$work/$1.exr" >/dev/null &
}
long=(--spp 96)
"$locus" render "$scene" "${long[@]}" -o "$work/single-long.exr" >/dev/null
lose() { # $1: what is done to the worker container $2 (kill | disconnect)
    submit_long "$1"
    local pid=$!
    wait_rendering
    case $1 in
        kill) docker kill "$2" >/dev/null ;;
        disconnect) docker network disconnect "$network" "$2" ;;
    esac
    echo "   $1: worker container ${2:0:12} lost mid-job" >&2
    wait "$pid" || fail "the job with a worker lost ($1) failed"
    "$locus" diff --exact "$work/$1.exr" "$work/single-long.exr" ||
        fail "the job with a worker lost ($1) differs from one machine"
    python3 -c 'import json,sys; r=json.load(open(sys.argv[1]))["farm"]["recovery"]; print("   attempts:", r["attempts"], "lost:", r["lost"], "tile passes kept:", r["tile_passes_kept"]); sys.exit(0 if r["lost"] else 1)' \
        "$work/$1.json" >&2 || fail "the report of the $1 job names no lost worker"
}
mapfile -t workers < <(dc ps -q worker)
((${#workers[@]} == 3)) || fail "expected 3 worker containers, found ${#workers[@]}"
network="$(docker network ls -q --filter "name=${project}_farm" | head -n 1)"
[[ -n "$network" ]] || fail "the farm network ${project}_farm is missing"
lose kill "${workers[1]}"
docker start "${workers[1]}" >/dev/null
wait_registered "the killed worker, started again, did not rejoin"
lose disconnect "${workers[2]}"
docker network connect "$network" "${workers[2]}"
wait_registered "the cut-off worker, connected again, did not rejoin"
echo "test-compose: ok: killed and cut-off workers lost mid-job, both jobs bit-identical, both workers back" >&2

echo "== 4b. the scheduler killed mid-job and started again on its state volume" >&2
submit_long restart
pid=$!
# Enough tiles in that some are in the store (its writer commits within
# milliseconds).
wait_rendering 16
sleep 0.5
scheduler="$(dc ps -q scheduler)"
docker kill "$scheduler" >/dev/null
docker start "$scheduler" >/dev/null
echo "   scheduler container ${scheduler:0:12} killed and started again mid-job" >&2
wait "$pid" || fail "the job did not survive the scheduler's restart"
"$locus" diff --exact "$work/restart.exr" "$work/single-long.exr" ||
    fail "the job resumed after the scheduler's restart differs from one machine"
python3 -c 'import json,sys; r=json.load(open(sys.argv[1]))["farm"]["recovery"]; print("   tile passes kept from the store:", r["tile_passes_kept"]); sys.exit(0 if r["tile_passes_kept"] > 0 else 1)' \
    "$work/restart.json" >&2 || fail "the resumed job kept no tiles from the store"
wait_registered "the workers did not register again with the restarted scheduler"
echo "test-compose: ok: the scheduler restarted mid-job, the job resumed from its store bit-identical" >&2

echo "== 5. down" >&2
