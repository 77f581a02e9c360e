#!/usr/bin/env bash
# The dependency bounds in pyproject.toml hold together: for every supported Python and
# both wheel platforms, resolve them at their lowest (uv's lowest-direct) and at their
# highest versions, wheels only, on manylinux2014. A bound that needs a source build
# or that contradicts another package's requirements fails here. (The lowest set is run
# for real by scripts/wheel_smoke.sh.)
# Usage: bash scripts/check_dependency_bounds.sh   (needs uv, `pip install uv`, and PyPI access)
set -euo pipefail
cd "$(dirname "$0")/.."
run_uv() { if command -v uv >/dev/null 2>&1; then uv "$@"; else python3 -m uv "$@"; fi; }
fail=0
for platform in x86_64-manylinux_2_17 aarch64-manylinux_2_17; do
    for py in 3.9 3.10 3.11 3.12 3.13; do
        for resolution in lowest-direct highest; do
            if out=$(run_uv pip compile pyproject.toml --python-version "$py" \
                --python-platform "$platform" --resolution "$resolution" \
                --only-binary :all: --no-header --no-annotate -q 2>&1); then
                echo "ok   $platform python $py $resolution: $(echo "$out" | tr '\n' ' ')"
            else
                echo "FAIL $platform python $py $resolution:"; echo "$out"; fail=1
            fi
        done
    done
done
exit $fail
