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
# The 20 resolutions wait on the index, not the CPU: run them at once, report in order.
out_dir=$(mktemp -d)
trap 'rm -rf "$out_dir"' EXIT
cases=()
for platform in x86_64-manylinux_2_17 aarch64-manylinux_2_17; do
    for py in 3.9 3.10 3.11 3.12 3.13; do
        for resolution in lowest-direct highest; do
            case_name="$platform python $py $resolution"
            cases+=("$case_name")
            (
                if run_uv pip compile pyproject.toml --python-version "$py" \
                    --python-platform "$platform" --resolution "$resolution" \
                    --only-binary :all: --no-header --no-annotate -q \
                    > "$out_dir/${#cases[@]}.out" 2>&1; then
                    echo ok > "$out_dir/${#cases[@]}.rc"
                else
                    echo FAIL > "$out_dir/${#cases[@]}.rc"
                fi
            ) &
        done
    done
done
wait
fail=0
for i in "${!cases[@]}"; do
    n=$((i + 1))
    if [ "$(cat "$out_dir/$n.rc" 2>/dev/null)" = ok ]; then
        echo "ok   ${cases[$i]}: $(tr '\n' ' ' < "$out_dir/$n.out")"
    else
        echo "FAIL ${cases[$i]}:"; cat "$out_dir/$n.out"; fail=1
    fi
done
exit $fail
