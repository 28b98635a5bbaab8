#!/usr/bin/env bash
# Sets up and runs the main job on the embedded default: builds `harmonize`
# (release), prepares .venv with ONNX Runtime for the neural backend, and runs
# `harmonize demo`, which enhances the bundled synthetic sequence (holes, an
# inserted object, flicker) and writes the frames and a before/after contact
# sheet under out/demo (or the directory given).
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$HOME/.cargo/bin:$PATH"
out=${1:-out/demo}
ort_line=$(./scripts/setup-venv.sh | tail -n 1)
export "${ort_line?}"
cargo build --release --locked -p harmonizer-cli
exec ./target/release/harmonize demo --out "$out"
