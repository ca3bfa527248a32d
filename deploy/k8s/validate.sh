#!/usr/bin/env bash
# Validates the manifests against the Kubernetes API schemas (strict:
# unknown fields fail) with kubernetes-validate from PyPI, installing it if
# missing, and checks that each worker's memory request and limit equal its
# --memory-budget and its CPU request its --threads. .ci/run runs this.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
if ! command -v kubernetes-validate >/dev/null 2>&1; then
    python3 -m pip install --quiet --disable-pip-version-check 'kubernetes-validate==1.37.*'
fi
manifests=("$here"/namespace.yaml "$here"/scheduler.yaml "$here"/workers.yaml "$here"/secret.example.yaml)
for v in 1.29.0 1.37.0; do
    kubernetes-validate --strict --quiet -k "$v" "${manifests[@]}"
done
python3 - "$here/workers.yaml" <<'PY'
import re, sys, yaml

UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
def budget(s):  # locus's --memory-budget: binary suffixes
    m = re.fullmatch(r"([0-9.]+)([KMGT]?)(i?B)?", s)
    return int(float(m[1]) * UNITS[m[2]])
def quantity(s):  # Kubernetes memory quantities with binary suffixes
    m = re.fullmatch(r"([0-9.]+)([KMGT]i)?", s)
    return int(float(m[1]) * UNITS[(m[2] or "")[:1]])

checked = 0
for doc in yaml.safe_load_all(open(sys.argv[1])):
    if not doc or doc["kind"] != "StatefulSet":
        continue
    for c in doc["spec"]["template"]["spec"]["containers"]:
        args = c["args"]
        flag = lambda f: args[args.index(f) + 1]
        res = c["resources"]
        want = budget(flag("--memory-budget"))
        for where in ("requests", "limits"):
            got = quantity(res[where]["memory"])
            assert got == want, f"{c['name']}: {where}.memory {got} != --memory-budget {want}"
        cpu = res["requests"]["cpu"]
        assert str(cpu) == flag("--threads"), f"{c['name']}: cpu request {cpu} != --threads"
        checked += 1
assert checked, "no worker container found"
print(f"k8s: manifests valid; {checked} worker container(s) request what their budget says")
PY
