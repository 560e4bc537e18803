#!/usr/bin/env bash
# The scale-out run of docs/OPERATIONS.md: the same batch of tiny jobs through one coordinator
# with 1 and then with 4 worker processes (separate processes of this binary on loopback, as
# `docker compose up --scale worker=N` runs them), back to back in one run; prints each
# wall time and the throughput ratio. Usage: scripts/scale-out.sh [JOBS] (default 8).
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=${1:-8}
bin=${STYLENERF_BIN:-target/release/stylenerf}
[[ -x $bin ]] || cargo build --release --bin stylenerf
out=$(mktemp -d)
for workers in 1 4; do
  "$bin" --log warn bench chaos --jobs "$jobs" --kills 0 --workers "$workers" --seed 0 \
    > "$out/$workers.json"
done
python3 - "$out/1.json" "$out/4.json" <<'PY'
import json, sys
runs = [json.load(open(path)) for path in sys.argv[1:]]
for workers, r in zip((1, 4), runs):
    assert r["jobs_succeeded"] == r["jobs_acknowledged"] and not r["violations"], r
    jobs, wall = r["jobs_succeeded"], r["wall_secs"]
    print(f"{workers} worker(s): {jobs} jobs in {wall:.1f} s, {60 * jobs / wall:.2f} jobs/min")
print(f"throughput with 4 workers: {runs[0]['wall_secs'] / runs[1]['wall_secs']:.2f}x that of 1")
PY
rm -rf "$out"
