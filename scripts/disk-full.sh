#!/usr/bin/env bash
# The disk-full check of docs/BENCHMARKS.md (needs root for a small tmpfs): a coordinator whose
# database and store sit on a 20 MiB tmpfs; submissions while the disk is full fail cleanly;
# after space is freed every acknowledged submission must still be in the database after the
# coordinator stops. Usage: sudo scripts/disk-full.sh [path/to/stylenerf]
set -euo pipefail
bin=${1:-target/debug/stylenerf}
work=$(mktemp -d)
mnt="$work/disk"
mkdir -p "$mnt"
mount -t tmpfs -o size=20m tmpfs "$mnt"
cleanup() { kill "$coordinator" 2>/dev/null || true; wait 2>/dev/null || true; umount "$mnt"; rm -rf "$work"; }
trap cleanup EXIT

"$bin" scene generate --out "$work/scene" --size 16 --views 4 >/dev/null
style=$(ls "$work"/scene/images/*.png | head -n 1)
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$bin" --log warn coordinator --listen "127.0.0.1:$port" --metrics-listen off --insecure-no-auth \
  --database "$mnt/coordinator.db" --storage "$mnt/store" 2>"$work/coordinator.log" &
coordinator=$!
sleep 2
endpoint="http://127.0.0.1:$port"
submit() { "$bin" submit --endpoint "$endpoint" --data "$work/scene" --style "$style" --preset tiny 2>>"$work/submit.log"; }

acknowledged=0
jobs=()
for _ in 1 2 3; do job=$(submit) && { acknowledged=$((acknowledged + 1)); jobs+=("$job"); }; done
# Fill the disk, then write while it is full: submissions (store and database) and
# cancellations (database only).
dd if=/dev/zero of="$mnt/filler" bs=64k 2>/dev/null || true
refused=0
cancelled=()
for i in 0 1 2; do
  if submit >/dev/null; then acknowledged=$((acknowledged + 1)); else refused=$((refused + 1)); fi
  if "$bin" cancel --endpoint "$endpoint" "${jobs[$i]}" >/dev/null 2>>"$work/submit.log"; then
    cancelled+=("${jobs[$i]}")
  else
    refused=$((refused + 1))
  fi
done
rm -f "$mnt/filler"
for _ in 1 2 3 4 5 6; do submit >/dev/null && acknowledged=$((acknowledged + 1)); done
kill -TERM "$coordinator"; wait "$coordinator" || true
count() { python3 -c "import sqlite3,sys; print(sqlite3.connect(sys.argv[1]).execute(sys.argv[2]).fetchone()[0])" "$mnt/coordinator.db" "$1"; }
stored=$(count "select count(*) from jobs")
stored_cancels=$(count "select count(*) from jobs where state = 'cancelled'")
echo "acknowledged: $acknowledged submissions, ${#cancelled[@]} cancellations; refused while full: $refused"
echo "in the database after stop: $stored jobs, $stored_cancels cancelled"
grep -ho 'disk is full\|No space left on device' "$work/submit.log" | sort | uniq -c || true
[ "$stored" -eq "$acknowledged" ] && [ "$stored_cancels" -eq "${#cancelled[@]}" ]
