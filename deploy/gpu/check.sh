#!/usr/bin/env bash
# The trainer on a GPU: `superflow-trainer check` runs the same steps on one real batch
# from the same initial weights on the CPU (`flex`, the reference) and on the GPU
# (`wgpu`, Vulkan), for the tiny presets and for MinkUNet-34 + ViT-S/14 shapes (random
# weights, pixel stride 1 as the official pooling), compares every step's losses (within
# 1e-3 relative) and prints steps/s; GPU memory is sampled with nvidia-smi meanwhile.
#
#   cargo build --release --locked -p superflow-pipeline -p superflow-trainer \
#       --features superflow-trainer/wgpu && strip target/release/superflow-{pipeline,trainer}
#   deploy/gpu/check.sh [BATCH_FILE]
#
# From the repository root. Without BATCH_FILE it builds one (4 samples of the sample
# drive) with `superflow-pipeline batch`. SUPERFLOW_BIN (default target/release),
# SUPERFLOW_CHECK_OUT (default target/gpu-check: the tables, JSON and memory samples),
# SUPERFLOW_CHECK_STEPS (default 3), SUPERFLOW_CHECK_PRESETS (default "tiny minkunet34").
# The GPU side needs the Vulkan loader (libvulkan1) and the NVIDIA driver's Vulkan ICD.
# On a machine without an NVIDIA GPU it runs the CPU side of the tiny check, says that
# the GPU part is outstanding and exits 3.
set -euo pipefail

bin="${SUPERFLOW_BIN:-target/release}"
out="${SUPERFLOW_CHECK_OUT:-target/gpu-check}"
steps="${SUPERFLOW_CHECK_STEPS:-3}"
read -r -a presets <<< "${SUPERFLOW_CHECK_PRESETS:-tiny minkunet34}"
mkdir -p "$out"

for tool in superflow-pipeline superflow-trainer; do
    [[ -x "$bin/$tool" ]] || { echo "check.sh: $bin/$tool is missing (build it first, see the header)" >&2; exit 1; }
done

batch="${1:-$out/batch.bin}"
if [[ ! -f "$batch" ]]; then
    echo "== building a batch of 4 samples of recordings/drives/street_ros2.mcap -> $batch"
    "$bin/superflow-pipeline" batch --mcap recordings/drives/street_ros2.mcap \
        --batch-size 4 --out "$batch"
fi

preset_args() {
    case "$1" in
        tiny) echo "--unet tiny --vit tiny --pixel-stride 4" ;;
        minkunet34) echo "--unet minkunet34 --vit small --pixel-stride 1" ;;
        *) echo "check.sh: unknown preset $1 (tiny, minkunet34)" >&2; exit 1 ;;
    esac
}

gpu=""
if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    gpu="$(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | head -n 1)"
fi

if [[ -z "$gpu" ]]; then
    echo "== no NVIDIA GPU here: running the CPU reference of the tiny check only"
    read -r -a args <<< "$(preset_args tiny)"
    "$bin/superflow-trainer" check --batch "$batch" --backends flex --steps "$steps" \
        "${args[@]}" --json "$out/tiny-cpu.json" | tee "$out/tiny-cpu.md"
    echo "check.sh: NO GPU on this machine: the wgpu comparison and the GPU figures are OUTSTANDING" >&2
    exit 3
fi

echo "== GPU: $gpu"
if ! "$bin/superflow-trainer" check --help >/dev/null 2>&1; then
    echo "check.sh: $bin/superflow-trainer has no check command" >&2
    exit 1
fi
status=0
for preset in "${presets[@]}"; do
    read -r -a args <<< "$(preset_args "$preset")"
    echo "== $preset: flex vs wgpu, $steps steps"
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 200 \
        > "$out/$preset-memory.txt" 2>/dev/null &
    sampler=$!
    "$bin/superflow-trainer" check --batch "$batch" --backends flex,wgpu --steps "$steps" \
        "${args[@]}" --json "$out/$preset.json" | tee "$out/$preset.md" || status=$?
    kill "$sampler" 2>/dev/null || true
    wait "$sampler" 2>/dev/null || true
    peak="$(sort -n "$out/$preset-memory.txt" | tail -n 1)"
    echo "$preset: peak GPU memory in use ${peak:-?} MiB (nvidia-smi, whole GPU)" | tee -a "$out/$preset.md"
done
exit "$status"
