#!/usr/bin/env bash
# Sets up everything and runs every test of harmonizer: formatting, lints,
# docs, header drift, Rust unit and integration tests, the C/C++ host tests,
# the Python binding, the USD hook, the wheels (installed into a clean venv)
# and the Blender extension (real Blender),
# the training smoke test, and each fuzz target for a short fixed time
# (HARMONIZER_FUZZ_SECONDS, 45 by default). Works on a fresh machine with
# only the package registries (creates .venv, .venv-bpy and .venv-usd as
# needed).
#
#   scripts/test.sh            # everything
#   scripts/test.sh rust c     # only some steps (names below)
#
# Every step runs even when an earlier one failed; the last line says
# "N passed, N failed" and the exit code is non-zero when any step failed.
set -uo pipefail
cd "$(dirname "$0")/.."
export PATH="$HOME/.cargo/bin:$PATH"

all_steps=(setup fmt clippy doc header rust release c python usd wheels blender training quality fuzz)
steps=("$@")
[ ${#steps[@]} -gt 0 ] || steps=("${all_steps[@]}")

passed=0
failed=0
failures=()

run_step() {
    local name=$1
    shift
    printf '\n==> %s: %s\n' "$name" "$*"
    local t0=$SECONDS
    if "$@"; then
        passed=$((passed + 1))
        printf '<== %s ok (%ss)\n' "$name" $((SECONDS - t0))
    else
        failed=$((failed + 1))
        failures+=("$name")
        printf '<== %s FAILED (%ss)\n' "$name" $((SECONDS - t0))
    fi
}

want() {
    local s
    for s in "${steps[@]}"; do [ "$s" = "$1" ] && return 0; done
    return 1
}

if want setup; then
    run_step setup ./scripts/setup-venv.sh
fi
ort_lib=$(ls "$PWD"/.venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* 2>/dev/null | sort | tail -n 1)
[ -n "$ort_lib" ] && export HARMONIZER_ORT_LIB="$ort_lib"

want fmt && run_step fmt cargo fmt --all -- --check
want clippy && run_step clippy cargo clippy --workspace --all-targets --locked -- -D warnings
want doc && run_step doc env RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked
want header && run_step header ./scripts/check-header.sh
want rust && run_step rust cargo test --workspace --locked --no-fail-fast
want release && run_step release cargo build --release --locked -p harmonizer-ffi -p harmonizer-cli
export HARMONIZER_LIB="$PWD/target/release/libharmonizer.so"
want c && run_step c-hosts make -C tests/c PROFILE=release
want c && run_step c-install ./tests/c/test_install.sh
want python && run_step python env PYTHONPATH="$PWD/ffi/python" .venv/bin/python -m pytest -q -p no:cacheprovider ffi/python/tests
want usd && run_step usd ./tests/usd/run.sh -q
# Issue 21: the wheels in a clean venv, no HARMONIZER_* variable, checkout untouched
# (cargo reuses the release build above).
want wheels && run_step wheels env CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}" ./tests/wheels/run.sh
want blender && run_step blender ./tests/blender/run.sh
want training && run_step training ./training/smoke_test.sh
want quality && run_step quality ./scripts/quality.sh --smoke
want fuzz && run_step fuzz ./scripts/fuzz.sh "${HARMONIZER_FUZZ_SECONDS:-45}"

printf '\n'
[ ${#failures[@]} -eq 0 ] || printf 'failed steps: %s\n' "${failures[*]}"
printf '%d passed, %d failed\n' "$passed" "$failed"
[ "$failed" -eq 0 ]
