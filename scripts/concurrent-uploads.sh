#!/usr/bin/env bash
# The concurrent-upload memory check of docs/BENCHMARKS.md: four submissions at once, each with
# an 8192×8192 16-bit PNG style, against a coordinator process; prints its peak RSS.
# Usage: scripts/concurrent-uploads.sh [path/to/stylenerf]
set -euo pipefail
bin=$(realpath "${1:-target/debug/stylenerf}")
work=$(mktemp -d)
trap 'kill "$coordinator" 2>/dev/null || true; rm -rf "$work"' EXIT
cd "$work"
python3 - <<'PY'
import struct, zlib
w = h = 8192
def chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
z = zlib.compressobj(9)
row = b"\x00" + b"\x80\x00" * 3 * w
idat = b"".join(z.compress(row) for _ in range(h)) + z.flush()
header = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
open("big.png", "wb").write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
PY
"$bin" scene generate --out scene --size 16 --views 4 >/dev/null
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$bin" --log warn coordinator --listen "127.0.0.1:$port" --metrics-listen off --insecure-no-auth \
  --database data/c.db --storage data/store 2>coordinator.log &
coordinator=$!
sleep 2
echo "idle: $(grep VmRSS /proc/$coordinator/status)"
pids=()
for i in 1 2 3 4; do
  "$bin" submit --endpoint "http://127.0.0.1:$port" --data scene --style big.png --preset tiny >"submit$i.out" 2>&1 &
  pids+=($!)
done
accepted=0
for pid in "${pids[@]}"; do wait "$pid" && accepted=$((accepted + 1)); done
echo "accepted $accepted of 4; peak: $(grep VmHWM /proc/$coordinator/status)"
