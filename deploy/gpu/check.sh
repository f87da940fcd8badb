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
# The GPU side needs the Vulkan loader (libvulkan1) and a Vulkan driver: the NVIDIA
# driver's ICD on an NVIDIA GPU (memory sampled with nvidia-smi), or any other Vulkan
# device wgpu finds (Mesa's software llvmpipe included: mesa-vulkan-drivers). The device
# used is printed (`wgpu device: NAME (software|hardware, ...)`); on a software device only
# the tiny preset runs (correctness, not speed). With no Vulkan device at all it runs the
# CPU side of the tiny check, says that the GPU part is outstanding and exits 3.
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

nvidia=""
if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
    nvidia="$(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | head -n 1)"
    echo "== NVIDIA GPU: $nvidia"
fi

run_check() { # preset, then the backends
    local preset="$1" backends="$2" sampler="" status=0
    read -r -a args <<< "$(preset_args "$preset")"
    echo "== $preset: $backends, $steps steps"
    if [[ -n "$nvidia" ]]; then
        nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 200 \
            > "$out/$preset-memory.txt" 2>/dev/null &
        sampler=$!
    fi
    "$bin/superflow-trainer" check --batch "$batch" --backends "$backends" --steps "$steps" \
        "${args[@]}" --json "$out/$preset.json" > "$out/$preset.md" 2> "$out/$preset.log" || status=$?
    cat "$out/$preset.md"
    if [[ -n "$sampler" ]]; then
        kill "$sampler" 2>/dev/null || true
        wait "$sampler" 2>/dev/null || true
        peak="$(sort -n "$out/$preset-memory.txt" | tail -n 1)"
        echo "$preset: peak GPU memory in use ${peak:-?} MiB (nvidia-smi, whole GPU)" | tee -a "$out/$preset.md"
    fi
    if (( status )); then
        tail -n 5 "$out/$preset.log" >&2
    fi
    return "$status"
}

# The tiny preset first: it says whether wgpu finds a Vulkan device at all, and which.
status=0
run_check tiny flex,wgpu || status=$?
device="$(sed -n 's/^wgpu device: //p' "$out/tiny.md" | head -n 1)"
if [[ -z "$device" ]]; then
    if grep -q "no device on this machine\|is not compiled in" "$out/tiny.log"; then
        echo "== no Vulkan device for wgpu here: running the CPU reference of the tiny check only"
        run_check tiny flex || true
        echo "check.sh: NO GPU on this machine: the wgpu comparison and the GPU figures are OUTSTANDING" >&2
        exit 3
    fi
    exit "$status"
fi
echo "== wgpu ran on: $device"
if [[ "$device" == *"(software"* ]]; then
    echo "== a software Vulkan device: the tiny preset only (correctness, not GPU speed)"
    exit "$status"
fi
for preset in "${presets[@]}"; do
    [[ "$preset" == tiny ]] && continue
    run_check "$preset" flex,wgpu || status=$?
done
exit "$status"
