#!/usr/bin/env bash
# Checks the protocol (run by .ci/run): `buf lint` with proto/buf.yaml, and `buf breaking`
# against the v1 baseline below: a field renumbered, retyped or removed, an RPC or message
# removed, fails CI. buf comes from npm (@bufbuild/buf ships its binary), installed in $TOOLS.
set -euo pipefail
cd "$(dirname "$0")/.."
TOOLS=${TOOLS:-target/ci-tools}
# The published v1 API every change must stay compatible with. Move it only on purpose.
BASELINE=0f9c9ab

npm install --prefix "$TOOLS/npm" --no-save --no-audit --no-fund --silent @bufbuild/buf@1.75.0
buf="$TOOLS/npm/node_modules/.bin/buf"
"$buf" lint proto
echo "buf lint: proto/ clean"
if git cat-file -e "$BASELINE^{commit}" 2>/dev/null; then
  # The baseline's proto/ is exported with git itself: buf's own `.git#ref=` input clones only
  # the newest 50 commits and so stops finding the baseline once main moves past it.
  against=$(mktemp -d)
  trap 'rm -rf "$against"' EXIT
  git archive "$BASELINE" proto | tar -x -C "$against"
  "$buf" breaking proto --against "$against/proto"
  echo "buf breaking: compatible with $BASELINE"
elif [[ $(git rev-parse --is-shallow-repository) == true ]]; then
  echo "buf breaking: skipped, $BASELINE is not in this shallow clone" >&2
else
  echo "buf breaking: the baseline $BASELINE is not in this repository" >&2
  exit 1
fi
