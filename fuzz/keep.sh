#!/usr/bin/env bash
# Keeps what a fuzzing run of TARGET found: its queue, minimised with
# afl-cmin, becomes fuzz/corpus/TARGET; each crash and hang goes to
# fuzz/regressions/TARGET (named by its hash), replayed by
# `cargo test -p locus-fuzz`.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
t="${1:?usage: fuzz/keep.sh TARGET}"
cd "$here"
export AFL_SKIP_CPUFREQ=1 AFL_I_DONT_CARE_ABOUT_MISSING_CRASHES=1
# afl.rs's AFL++ build; its afl-cmin.bash (the Python afl-cmin that
# `cargo afl cmin` runs found no coverage in this persistent-mode target).
bin="$(ls -d "${XDG_DATA_HOME:-$HOME/.local/share}"/afl.rs/rustc-*/afl.rs-*/afl/bin | tail -n 1)"
rm -rf "out/$t.min"
AFL_PATH="$bin" PATH="$bin:$PATH" "$bin/afl-cmin.bash" -i "out/$t/default/queue" -o "out/$t.min" \
    -- target/release/locus-afl "$t" >/dev/null 2>&1
[[ -n "$(ls -A "out/$t.min" 2>/dev/null)" ]] || { echo "afl-cmin kept nothing for $t" >&2; exit 1; }
rm -rf "corpus/$t" && mv "out/$t.min" "corpus/$t"
mkdir -p "regressions/$t"
for f in "out/$t/default/crashes"/id* "out/$t/default/hangs"/id*; do
    [[ -f "$f" ]] || continue
    cp "$f" "regressions/$t/crash-$(sha1sum "$f" | cut -c1-12)"
done
echo "$t: $(ls "corpus/$t" | wc -l) corpus inputs, $(ls "regressions/$t" | wc -l) regressions"
