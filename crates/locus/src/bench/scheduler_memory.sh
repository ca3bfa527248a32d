#!/usr/bin/env bash
# Resident memory of a scheduler daemon and its workers between jobs: a
# scheduler and two one-thread workers on this machine, JOBS jobs of SCENE
# submitted one after another (`adaptive`, two workers), and each
# process's VmRSS (/proc/PID/status) a second after each job, with the
# job's total time.
#
#   crates/locus/src/bench/scheduler_memory.sh [LOCUS] [SCENE] [JOBS] [PORT]
set -euo pipefail
bin=${1:-target/release/locus}
scene=${2:-scenes/generated/half.toml}
jobs=${3:-6}
port=${4:-7979}
out=$(mktemp -d)
"$bin" scheduler --listen "127.0.0.1:$port" --token bench > "$out/scheduler.log" 2>&1 &
s=$!
sleep 0.5
"$bin" worker --scheduler "127.0.0.1:$port" --listen 127.0.0.1:0 --token bench --threads 1 > "$out/w1.log" 2>&1 &
w1=$!
"$bin" worker --scheduler "127.0.0.1:$port" --listen 127.0.0.1:0 --token bench --threads 1 > "$out/w2.log" 2>&1 &
w2=$!
trap 'kill $s $w1 $w2 2>/dev/null; wait 2>/dev/null; rm -rf "$out"' EXIT
sleep 1
rss() { awk '/VmRSS/ { printf "%.1f", $2 / 1024 }' "/proc/$1/status"; }
echo "idle: scheduler $(rss $s) MiB, workers $(rss $w1) $(rss $w2) MiB"
for j in $(seq "$jobs"); do
    "$bin" submit --scheduler "127.0.0.1:$port" "$scene" -o "$out/job.exr" --workers 2 \
        --fetch adaptive --token bench > "$out/submit.log" 2>&1
    sleep 1
    echo "after job $j: scheduler $(rss $s) MiB, workers $(rss $w1) $(rss $w2) MiB," \
        "$(grep -o 'total [0-9.]*s' "$out/submit.log")"
done
