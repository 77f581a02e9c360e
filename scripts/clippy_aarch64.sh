#!/usr/bin/env bash
# clippy, warnings as errors, for aarch64-unknown-linux-gnu: the x86-64-only SIMD builds
# are compiled out there (`#[cfg(target_arch = "x86_64")]`), and what only they use must
# be compiled out with them, or the aarch64 wheel's build warns of dead code.
# Checks, does not link; a C dependency of the benchmarks (criterion's `alloca`) is
# compiled with zig (`pip install ziglang`, as the wheel build uses) for the target.
# Usage: bash scripts/clippy_aarch64.sh   (skips, exit 0, without the Rust target:
# `rustup target add aarch64-unknown-linux-gnu`)
set -euo pipefail
cd "$(dirname "$0")/.."
target=aarch64-unknown-linux-gnu
if ! rustup target list --installed 2>/dev/null | grep -qx "$target"; then
    echo "[clippy_aarch64] SKIPPED: the Rust target $target is not installed"
    exit 0
fi
py=${PYTHON:-python3}
zig=$("$py" -c 'import os, ziglang; print(os.path.join(os.path.dirname(ziglang.__file__), "zig"))') || {
    echo "[clippy_aarch64] needs zig: $py -m pip install ziglang" >&2
    exit 2
}
work=$(mktemp -d "${TMPDIR:-/tmp}/lfcam-clippy.XXXXXX")
trap 'rm -rf "$work"' EXIT
# cc-rs passes clang's --target spelling, which zig does not parse: zig gets its own.
cat > "$work/cc" <<SH
#!/usr/bin/env bash
args=()
for a in "\$@"; do case "\$a" in --target=*) ;; *) args+=("\$a") ;; esac; done
exec "$zig" cc -target aarch64-linux-gnu "\${args[@]}"
SH
printf '#!/bin/sh\nexec "%s" ar "$@"\n' "$zig" > "$work/ar"
chmod +x "$work/cc" "$work/ar"
CC_aarch64_unknown_linux_gnu="$work/cc" AR_aarch64_unknown_linux_gnu="$work/ar" \
    cargo clippy --workspace --all-targets --all-features --target "$target" -- -D warnings
