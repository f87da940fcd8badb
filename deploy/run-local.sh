#!/usr/bin/env bash
# The main job on one host: superflow-pipeline streams batches from the given drives
# (default: the sample drive) over iceoryx2 and one superflow-trainer trains on them.
# Usage: deploy/run-local.sh [DRIVE.mcap|DIR ...]
#
# Defaults are the CPU demo: the tiny 3D preset, a tiny RANDOM ViT (no DINOv2 weights;
# the trainer says so loudly), superpixel pooling at every 4th pixel, 48 steps.
# Real pretraining: TRAINER_ARGS="--unet minkunet34 --image-weights dinov2_vits14.safetensors
# --steps 100000 --pixel-stride 1" (and a GPU backend, see trainer/README.md).
# Output (metrics.jsonl, losses.svg, checkpoints/) goes to runs/<run>.
set -euo pipefail
cd "$(dirname "$0")/.."
drives=("$@")
[ ${#drives[@]} -gt 0 ] || drives=(recordings/drives/street_ros2.mcap)
run="${RUN:-local}"
export SUPERFLOW_IOX_PREFIX="${SUPERFLOW_IOX_PREFIX:-sf$$}"
read -r -a trainer_args <<< "${TRAINER_ARGS:---unet tiny --vit tiny --pixel-stride 4 --steps 48}"

cargo build --release -p superflow-pipeline -p superflow-trainer
rm -rf "runs/$run"
./target/release/superflow-pipeline --mcap "${drives[@]}" --run "$run" --batch-size 2 &
pipeline=$!
trap 'kill -TERM "$pipeline" 2>/dev/null || true' EXIT
status=0
./target/release/superflow-trainer --run "$run" --plot "${trainer_args[@]}" || status=$?
# The trainer is done: stop the pipeline (SIGTERM: the batch in flight finishes and the
# shared memory is released).
kill -TERM "$pipeline" 2>/dev/null || true
wait "$pipeline" || true
[ "$status" -ne 0 ] || echo "trained: runs/$run/metrics.jsonl, runs/$run/losses.svg, runs/$run/checkpoints/"
exit "$status"
