#!/usr/bin/env bash
# Run the coverage-guided fuzz targets one after another (docs/bad-input.md, "Fuzzing").
#   fuzz/run.sh [SECONDS] [TARGET...]     default: 600 s each, every target
# Needs cargo-fuzz (`cargo install cargo-fuzz`); the stable compiler builds libFuzzer targets with
# RUSTC_BOOTSTRAP=1. Corpora grow in fuzz/corpus/TARGET, crashes land in fuzz/artifacts/TARGET,
# logs in fuzz/logs/TARGET.log (the last lines carry the figures: execs, cov, ft, corpus).
set -euo pipefail
cd "$(dirname "$0")"
secs=${1:-600}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    mapfile -t targets < <(RUSTC_BOOTSTRAP=1 cargo fuzz list)
fi
mkdir -p logs
# The targets write every input to a file before parsing it: keep those writes in memory, so a
# slow disk shows up as nothing; -timeout=300 rides out the stalls of this shared machine.
if [ -z "${TMPDIR:-}" ] && [ -d /dev/shm ]; then
    export TMPDIR=/dev/shm
fi
for t in "${targets[@]}"; do
    echo "== $t ($secs s)"
    RUSTC_BOOTSTRAP=1 nice -n 10 cargo fuzz run "$t" -- \
        -max_total_time="$secs" -timeout=300 -rss_limit_mb=2048 -print_final_stats=1 \
        >"logs/$t.log" 2>&1 || echo "$t: exit $? (see fuzz/logs/$t.log and fuzz/artifacts/$t)"
    grep -E '^#[0-9]+.*(DONE|cov:)' "logs/$t.log" | tail -n 1 || true
    grep -E '^stat::' "logs/$t.log" || true
done
