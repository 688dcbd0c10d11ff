#!/usr/bin/env bash
# Validates the Kubernetes manifest(s) offline, strictly (unknown fields are errors), against
# the schemas that the kubernetes-validate package ships, for one Kubernetes version.
#
#   scripts/cluster/check-k8s-manifest.sh PYTHON [MANIFEST...]
#   PYTHON=target/venv/bin/python scripts/cluster/check-k8s-manifest.sh [MANIFEST...]
#
# PYTHON (first argument or env PYTHON) is the interpreter of a virtual environment;
# kubernetes-validate is pip-installed into it (quietly) when it cannot import it, which
# needs the package index once. MANIFEST defaults to scripts/cluster/k8s-indexed-job.yaml.
# Environment:
#   K8S_VERSION                  Kubernetes version to validate against (default 1.30.0,
#                                the oldest with every field the Job uses, podFailurePolicy,
#                                podReplacementPolicy, on by default)
#   KUBERNETES_VALIDATE_VERSION  version of kubernetes-validate to install (default 1.37.0)
# Exit status 0 when every resource validates; 1 with the validator's messages on stderr
# otherwise; 2 on a usage error.
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
K8S_VERSION="${K8S_VERSION:-1.30.0}"
KUBERNETES_VALIDATE_VERSION="${KUBERNETES_VALIDATE_VERSION:-1.37.0}"

py="${PYTHON:-}"
case "${1:-}" in
*.yaml | *.yml) ;;                       # no interpreter argument: PYTHON from the environment
*) py="${1:-$py}"; [ $# -eq 0 ] || shift ;;
esac
if [ -z "$py" ]; then
    echo "usage: $0 PYTHON [MANIFEST...]   (or PYTHON=... $0): a virtual environment's python" >&2
    exit 2
fi
if ! "$py" -c 'import sys' 2>/dev/null; then
    echo "check-k8s-manifest: '$py' is not a working Python interpreter" >&2
    exit 2
fi
manifests=("$@")
((${#manifests[@]})) || manifests=("$repo/scripts/cluster/k8s-indexed-job.yaml")

if ! "$py" -c 'import kubernetes_validate' 2>/dev/null; then
    echo "check-k8s-manifest: installing kubernetes-validate==$KUBERNETES_VALIDATE_VERSION into $py"
    if ! pip_out="$("$py" -m pip install -q --disable-pip-version-check \
        "kubernetes-validate==$KUBERNETES_VALIDATE_VERSION" 2>&1)"; then
        printf '%s\n' "$pip_out" >&2
        echo "check-k8s-manifest: could not install kubernetes-validate into $py" >&2
        exit 1
    fi
fi

# --quiet prints only warnings and failures; the exit status is non-zero on any failure.
if out="$("$py" -m kubernetes_validate --strict --quiet -k "$K8S_VERSION" "${manifests[@]}" 2>&1)"; then
    [ -z "$out" ] || printf '%s\n' "$out"
    echo "check-k8s-manifest: ${manifests[*]}: valid (Kubernetes $K8S_VERSION, strict)"
else
    printf '%s\n' "$out" >&2
    echo "check-k8s-manifest: ${manifests[*]}: INVALID against Kubernetes $K8S_VERSION (strict)" >&2
    exit 1
fi
