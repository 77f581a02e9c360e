#!/usr/bin/env bash
# Build lfcam's release wheel as lab machines get it, check it, install it where no Rust
# toolchain exists and run it:
#   1. `maturin build --release --zig --compatibility manylinux2014 --target T --strip`
#      (zig links against glibc 2.17 symbols, no container needed; one abi3 wheel per
#      platform, without the test-only cargo feature);
#   2. `auditwheel show`: the tag must be manylinux2014 (manylinux_2_17) or older, and the
#      extension must carry no symbol table or debug info;
#   3. a fresh venv, PATH without cargo or rustc, `pip install` the wheel, then
#      `lfcam --version` and `lfcam demo --quick` (simulate, calibrate and process a
#      small camera), and build_info() must show a release build; then the same demo
#      with the lowest dependency versions pyproject.toml allows (uv's lowest-direct
#      resolution, wheels only).
# Usage: bash scripts/wheel_smoke.sh [--target x86_64-unknown-linux-gnu|aarch64-unknown-linux-gnu]
#                                    [--out DIR] [--wheel FILE] [--no-smoke]
#   --wheel FILE: check and smoke-test an already built wheel (no build).
#   A wheel for another architecture is built and checked but not run.
# Needs: Python >= 3.9 with venv, a Rust toolchain with the target's standard library
# (`rustup target add aarch64-unknown-linux-gnu` for the second), PyPI access.
set -euo pipefail
cd "$(dirname "$0")/.."

target=x86_64-unknown-linux-gnu
out=dist
wheel=
smoke=1
while [ $# -gt 0 ]; do
    case "$1" in
        --target) target=$2; shift 2 ;;
        --out) out=$2; shift 2 ;;
        --wheel) wheel=$2; shift 2 ;;
        --no-smoke) smoke=0; shift ;;
        *) echo "wheel_smoke.sh: unknown argument $1" >&2; exit 2 ;;
    esac
done
arch=${target%%-*}
py=${PYTHON:-python3}
work=$(mktemp -d "${TMPDIR:-/tmp}/lfcam-wheel.XXXXXX")
prepare_pids=()  # background installs (below), stopped on exit
trap 'kill "${prepare_pids[@]}" 2>/dev/null || true; rm -rf "$work"' EXIT
trap 'exit 130' INT TERM  # the EXIT trap cleans up on a signal too
say() { echo "[wheel_smoke] $*"; }

# Tools in their own venv: auditwheel, uv (the lowest-versions resolution) and, to
# build, maturin and zig (the ziglang wheel ships the compiler).
"$py" -m venv "$work/tools"
tools="$work/tools/bin"
"$tools/python" -m pip install -q "auditwheel>=6" "uv>=0.4"
if [ -z "$wheel" ]; then
    "$tools/python" -m pip install -q "maturin>=1.5,<2" "ziglang>=0.11"
fi

# The smoke venvs' dependencies install (network-bound) while the wheel builds (CPU-bound):
# the newest versions pyproject.toml allows in one venv, the lowest in the other.
pyver=$("$py" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
prepare_venv() {  # NAME RESOLUTION
    "$tools/uv" pip compile pyproject.toml --resolution "$2" --python-version "$pyver" \
        --only-binary :all: --no-header --no-annotate -q -o "$work/$1.txt"
    "$py" -m venv "$work/$1"
    "$work/$1/bin/python" -m pip install -q -r "$work/$1.txt"
}
if [ "$smoke" = 1 ] && [ "$arch" = "$(uname -m)" ]; then
    for setup in "smoke highest" "lowest lowest-direct"; do
        # shellcheck disable=SC2086
        prepare_venv $setup > "$work/prepare-${setup%% *}.log" 2>&1 &
        prepare_pids+=($!)
    done
fi
prepared() {  # wait for the venvs; show a failed preparation's log
    local ok=0
    for pid in "${prepare_pids[@]}"; do wait "$pid" || ok=1; done
    if [ "$ok" != 0 ]; then
        cat "$work"/prepare-*.log >&2
        echo "wheel_smoke.sh: installing the smoke venvs' dependencies failed" >&2
        exit 1
    fi
}

if [ -z "$wheel" ]; then
    say "building the $target wheel (release, manylinux2014, abi3, stripped)"
    t0=$(date +%s)
    mkdir -p "$out"
    rm -f "$out"/lfcam-*-"$arch"*.whl "$out"/lfcam-*_"$arch".whl
    # maturin finds zig through the ziglang package of the interpreter running it.
    PATH="$tools:$PATH" "$tools/maturin" build --release --zig \
        --compatibility manylinux2014 --target "$target" --strip --out "$out"
    wheel=$(ls -t "$out"/lfcam-*.whl | head -n 1)
    say "built $wheel in $(( $(date +%s) - t0 )) s"
fi
wheel=$(cd "$(dirname "$wheel")" && pwd)/$(basename "$wheel")
case "$(basename "$wheel")" in
    *-cp39-abi3-*) ;;
    *) echo "wheel_smoke.sh: $wheel is not an abi3 (cp39-abi3) wheel" >&2; exit 1 ;;
esac

say "auditwheel show"
show=$("$tools/auditwheel" show "$wheel")
echo "$show"
tag=$(printf '%s\n' "$show" | grep -o 'manylinux_2_[0-9]*_[a-z0-9_]*' | head -n 1 || true)
minor=$(printf '%s\n' "$tag" | sed -n 's/^manylinux_2_\([0-9]*\)_.*/\1/p')
if [ -z "$minor" ] || [ "$minor" -gt 17 ]; then
    echo "wheel_smoke.sh: $wheel: platform tag '${tag:-none}' is newer than manylinux2014 (manylinux_2_17)" >&2
    exit 1
fi
say "platform tag $tag: manylinux2014 or older"

# Stripped: no symbol table, no DWARF in the extension.
"$tools/python" - "$wheel" "$work/unpacked" <<'PY'
import sys, zipfile
from pathlib import Path

wheel, dest = sys.argv[1], Path(sys.argv[2])
with zipfile.ZipFile(wheel) as z:
    names = [n for n in z.namelist() if n.endswith(".so")]
    assert names == ["lfcam/_lfcam.abi3.so"], f"{wheel}: extension files {names}"
    so = z.read(names[0])
# ELF section names from the section header string table.
import struct
assert so[:4] == b"\x7fELF", "not an ELF file"
is64, little = so[4] == 2, so[5] == 1
e = "<" if little else ">"
shoff = struct.unpack_from(e + ("Q" if is64 else "I"), so, 0x28 if is64 else 0x20)[0]
shentsize, shnum, shstrndx = struct.unpack_from(e + "HHH", so, 0x3A if is64 else 0x2E)
def sect(i):
    off = shoff + i * shentsize
    if is64:
        name, _, _, _, offset, size = struct.unpack_from(e + "IIQQQQ", so, off)
    else:
        name, _, _, _, offset, size = struct.unpack_from(e + "IIIIII", so, off)
    return name, offset, size
_, stroff, strsize = sect(shstrndx)
strtab = so[stroff : stroff + strsize]
sections = {strtab[n : strtab.index(b"\0", n)].decode() for n, _, _ in map(sect, range(shnum))}
bad = sorted(s for s in sections if s == ".symtab" or s.startswith(".debug"))
assert not bad, f"{wheel}: the extension is not stripped: {bad}"
print(f"[wheel_smoke] extension stripped ({len(so) / 1e6:.1f} MB, no .symtab or .debug_*)")
PY

if [ "$smoke" = 0 ]; then
    say "smoke test skipped (--no-smoke)"
    exit 0
fi
if [ "$arch" != "$(uname -m)" ]; then
    say "smoke test skipped: a $arch wheel does not run on this $(uname -m) machine"
    exit 0
fi

say "smoke test: a fresh venv with no Rust toolchain on PATH"
prepared
clean_path="$work/smoke/bin:/usr/local/bin:/usr/bin:/bin"
for tool in cargo rustc rustup; do
    if PATH="$clean_path" command -v "$tool" >/dev/null 2>&1; then
        echo "wheel_smoke.sh: $tool is on the smoke test's PATH ($clean_path)" >&2
        exit 1
    fi
done
(
    cd "$work"  # not the source tree: python must import the installed package
    export PATH="$clean_path"
    unset CARGO_HOME RUSTUP_HOME VIRTUAL_ENV PYTHONPATH
    python -m pip install -q "$wheel"
    lfcam --version
    python - <<'PY'
import lfcam

info = lfcam.build_info()
assert not info["test_hooks"], "a release wheel must not carry the test hooks"
assert lfcam.__file__.startswith(__import__("sys").prefix), lfcam.__file__
print("[wheel_smoke] build_info:", info)
PY
    t0=$(date +%s)
    lfcam demo --quick "$work/demo"
    test -f "$work/demo/camera.lfcal"
    test -f "$work/demo/results/planes/depth.tiff"
    echo "[wheel_smoke] demo --quick took $(( $(date +%s) - t0 )) s"
)

say "smoke test at the lowest dependency versions pyproject.toml allows"
tr '\n' ' ' < "$work/lowest.txt"; echo
(
    cd "$work"
    export PATH="$work/lowest/bin:/usr/local/bin:/usr/bin:/bin"
    unset CARGO_HOME RUSTUP_HOME VIRTUAL_ENV PYTHONPATH
    python -m pip install -q --no-deps "$wheel"
    # To a file, then its head: piping the demo into `head` would end it with SIGPIPE
    # (exit 141) whenever head closes the pipe before the demo's last line.
    lfcam demo --quick "$work/demo-lowest" > "$work/demo-lowest.log"
    head -n 4 "$work/demo-lowest.log"
)
say "ok: $wheel"
