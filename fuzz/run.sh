#!/usr/bin/env bash
# Fuzzes one target with AFL++ (afl.rs, stable Rust) until it has run
# EXECS executions (default 10 million), starting from fuzz/corpus/TARGET
# and writing AFL's state to fuzz/out/TARGET (git ignores it).
#   cargo install cargo-afl && cargo afl config --build   # once
#   fuzz/run.sh obj            # scene_toml obj mtl ply gltf glb frames
#   fuzz/run.sh all 1000000    # every target in turn
# Afterwards: fuzz/keep.sh TARGET minimises the corpus back into
# fuzz/corpus/TARGET and copies crashes to fuzz/regressions/TARGET, where
# `cargo test -p locus-fuzz` replays them.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
target="${1:?usage: fuzz/run.sh TARGET|all [EXECS]}"
execs="${2:-10000000}"
cd "$here"
cargo afl build --release
export AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1 AFL_NO_UI=1
if [[ "$target" == all ]]; then
    set -- scene_toml obj mtl ply gltf glb frames
else
    set -- "$target"
fi
for t in "$@"; do
    mkdir -p out
    # -E: stop after this many executions; -t: a run over 1 s is a hang.
    cargo afl fuzz -i "corpus/$t" -o "out/$t" -E "$execs" -t 1000 -- target/release/locus-afl "$t" \
        >"out/$t.log" 2>&1 || { tail -20 "out/$t.log" >&2; exit 1; }
    grep -E '^(execs_done|execs_per_sec|corpus_count|saved_crashes|saved_hangs)' "out/$t/default/fuzzer_stats" |
        tr -s ' ' | sed "s/^/$t: /"
done
