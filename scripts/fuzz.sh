#!/usr/bin/env bash
# Runs the fuzz targets of fuzz/ (cargo-fuzz, libFuzzer with AddressSanitizer,
# on the nightly toolchain), each for SECONDS, starting from the committed
# seeds (fuzz/seeds/<target>) and the local corpus (fuzz/corpus/<target>,
# not committed). A crash, a leak, an allocation over the malloc limit or a
# slow input fails the run; the input is saved under fuzz/artifacts/<target>.
#
#   scripts/fuzz.sh                   # every target for 45 s (what CI runs)
#   scripts/fuzz.sh 3600 exr_read     # one target for an hour
#   scripts/fuzz.sh 600 exr_read manifest
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="${CARGO_HOME:-$HOME/.cargo}/bin:$HOME/.cargo/bin:$PATH"

secs=${1:-45}
[ $# -gt 0 ] && shift
targets=("$@")
[ ${#targets[@]} -gt 0 ] || targets=(exr_read manifest frame_desc)

if ! rustup run nightly rustc --version >/dev/null 2>&1; then
    echo "fuzz: cargo-fuzz needs the nightly toolchain (rustup toolchain install nightly)" >&2
    exit 1
fi
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    echo "fuzz: installing cargo-fuzz 0.13.2 from crates.io"
    cargo +nightly install cargo-fuzz --version 0.13.2 --locked --quiet
fi

cd fuzz
cargo +nightly fuzz build -O
status=0
for t in "${targets[@]}"; do
    mkdir -p "corpus/$t" "artifacts/$t"
    log=$(mktemp)
    # 2 GiB of RSS, and no single allocation above it: a hostile claim the
    # library passed on to the allocator shows up as a failure here.
    if cargo +nightly fuzz run -O "$t" "corpus/$t" "seeds/$t" -- \
        -max_total_time="$secs" -rss_limit_mb=2048 -timeout=20 \
        -print_final_stats=1 >"$log" 2>&1; then
        result=ok
    else
        result=FAILED
        status=1
        tail -n 60 "$log"
    fi
    runs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -n 1)
    printf 'fuzz %s: %s, %s executions in %s s, corpus %s inputs\n' \
        "$t" "$result" "${runs:-?}" "$secs" "$(ls "corpus/$t" | wc -l)"
    rm -f "$log"
done
exit $status
