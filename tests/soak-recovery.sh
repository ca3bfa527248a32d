#!/usr/bin/env bash
# The worker-loss soak: the recovery test's kill -9 loop (a scheduler and
# three worker daemons on loopback, one worker killed at a random moment of
# every job, then started again) for many more jobs than CI runs, each
# checked bit for bit against one machine's render.
#   tests/soak-recovery.sh [RUNS]     (default 500; about 0.4 s a run)
set -euo pipefail
cd "$(dirname "$0")/.."
LOCUS_SOAK_RUNS="${1:-500}" cargo test --release -p locus --test recovery \
    -- --nocapture jobs_survive_a_worker_killed_at_random_moments
