#!/usr/bin/env bash
# The quality benchmark: harmonizer against identity, OpenCV inpainting
# (Telea, Navier-Stokes), Open Image Denoise per frame, a reprojected moving
# average and OIDN followed by it, on the out-of-domain renders committed in
# training/ood/data and, when rendered, the training generator's held-out
# scenes. Writes out/quality/{metrics.json,report.md,per_frame_*.png,strips/}.
#
#   scripts/quality.sh --quick             # 12 frames a sequence, one in-domain scene (~5 min after the build)
#   scripts/quality.sh                     # every frame and scene
#   scripts/quality.sh --render-in-domain  # first render the held-out scenes 9, 19, 29 (Blender; root for apt-get)
#   scripts/quality.sh --render-ood        # first re-render the out-of-domain scenes (Blender, about 50 min)
#   scripts/quality.sh --smoke             # CI: the harness's tests and 3 frames of 3 sequences
#   scripts/quality.sh --out DIR ...       # other arguments go to training/quality.py
set -euo pipefail
cd "$(dirname "$0")/.."
export PATH="$HOME/.cargo/bin:$PATH"
python="${PYTHON:-python3.11}"
args=()
render_in=0
render_ood=0
smoke=0
for a in "$@"; do
    case "$a" in
        --render-in-domain) render_in=1 ;;
        --render-ood) render_ood=1 ;;
        --smoke) smoke=1 ;;
        *) args+=("$a") ;;
    esac
done

venv=.venv-quality
if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
if ! "$venv/bin/python" -c "import cv2, pyoidn, OpenEXR, matplotlib, onnxruntime, pytest" 2>/dev/null; then
    "$venv/bin/pip" install --quiet --disable-pip-version-check -r training/requirements-quality.txt
fi
ort=$(ls "$PWD/$venv"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* | head -n 1)
export HARMONIZER_ORT_LIB="$ort"

if [ "$render_ood" = 1 ] || [ "$render_in" = 1 ]; then
    training/setup_env.sh bpy
fi
if [ "$render_ood" = 1 ]; then
    for s in courtyard hall ruins; do
        rm -rf "training/ood/data/$s"
        nice -n 5 .venv-bpy/bin/python -m training.ood.render --scene "$s" --out training/ood/data
    done
fi
if [ "$render_in" = 1 ]; then
    .venv-bpy/bin/python -m training.synth.assets
    for id in 9 19 29; do
        nice -n 5 .venv-bpy/bin/python -m training.synth.generate --out training/data --scenes "$id:$((id + 1))"
    done
fi

cargo build --release --locked -p harmonizer-cli
if [ "$smoke" = 1 ]; then
    PYTHONPATH="$PWD" "$venv/bin/python" -m pytest -q -p no:cacheprovider training/tests/test_quality.py
    out=out/quality-smoke
    rm -rf "$out"
    "$venv/bin/python" -m training.quality --harmonize target/release/harmonize --out "$out" --frames 3 \
        --sets ood --only recon_hall,insert_control,noisy_raw
    for f in metrics.json report.md per_frame_ood.png strips/recon_hall.png; do
        [ -s "$out/$f" ] || { echo "quality: $out/$f was not written" >&2; exit 1; }
    done
    exit 0
fi
exec "$venv/bin/python" -m training.quality --harmonize target/release/harmonize "${args[@]}"
