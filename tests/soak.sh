#!/usr/bin/env bash
# Soak: the pipeline streams to two trainers (shard mode, tiny presets) for a set time.
# Every process's resident memory (RSS) is read every 5 s and its peak over each
# interval (default a minute) is recorded, with the bytes held in /dev/shm and the
# steps trained. Training memory is a sawtooth (batches alternate ~106k / ~55k points),
# so growth is judged on peaks: memory is flat when no process's peak in the second half
# of the run (after the warm-up) exceeds its peak in the first half by more than
# max(5 % of that peak, 16 MiB). A least-squares slope is printed too. Exits 1 when a
# process grows, dies, or leaves files in /dev/shm. Not part of `cargo test`.
#
# Usage: tests/soak.sh [MINUTES]            (default 30)
#        tests/soak.sh --analyze rss.csv    (the verdict on a recorded run)
#   SOAK_INTERVAL_SECS=60  recording interval
#   SOAK_WARMUP_MINUTES=3  not judged before this (allocators and caches fill)
#   SOAK_DRIVES="recordings/drives"  what the pipeline streams
#   SOAK_OUT=runs/soak     rss.csv, summary.txt, the processes' logs and outputs
#   SOAK_NICE=0            niceness of the processes (e.g. 10 on a shared machine)
set -euo pipefail
cd "$(dirname "$0")/.."
warmup="${SOAK_WARMUP_MINUTES:-3}"

# The verdict: columns 2..5 of the CSV (minute, then one KiB column per process).
analyze() { # CSV LEFT_IN_SHM
    awk -F, -v warmup="$warmup" -v left="$2" '
    NR == 1 { for (i = 2; i <= 5; i++) name[i] = $i; next }
    $1 >= warmup { n++; x[n] = $1; for (i = 2; i <= 5; i++) y[n, i] = $i / 1024 }
    END {
        if (n < 4) { print "soak: fewer than 4 samples after the warm-up; run longer"; exit 1 }
        half = int(n / 2); bad = 0
        printf "%-12s %9s %9s %13s %13s %12s %12s  %s\n", "process", "min MiB", "max MiB",
            "peak 1st half", "peak 2nd half", "growth MiB", "slope MiB/h", "verdict"
        for (i = 2; i <= 5; i++) {
            lo = hi = y[1, i]; p1 = p2 = 0; sx = sy = sxx = sxy = 0
            for (k = 1; k <= n; k++) {
                v = y[k, i]; if (v < lo) lo = v; if (v > hi) hi = v
                if (k <= half) { if (v > p1) p1 = v } else { if (v > p2) p2 = v }
                sx += x[k]; sy += v; sxx += x[k] * x[k]; sxy += x[k] * v
            }
            d = n * sxx - sx * sx; slope = d > 0 ? (n * sxy - sx * sy) / d : 0
            growth = p2 - p1; limit = p1 * 0.05 > 16 ? p1 * 0.05 : 16
            verdict = growth <= limit ? "flat" : "GROWS"; if (growth > limit) bad = 1
            printf "%-12s %9.1f %9.1f %13.1f %13.1f %12.1f %12.1f  %s (limit %.1f)\n",
                name[i], lo, hi, p1, p2, growth, slope * 60, verdict, limit
        }
        printf "judged %d samples from minute %.1f to %.1f (warm-up %s min); files left in /dev/shm: %s\n",
            n, x[1], x[n], warmup, left
        if (left != "" && left > 0) bad = 1
        exit bad
    }' "$1"
}

if [ "${1:-}" = "--analyze" ]; then
    analyze "${2:?usage: $0 --analyze rss.csv}" ""
    exit
fi

minutes="${1:-30}"
interval="${SOAK_INTERVAL_SECS:-60}"
out="${SOAK_OUT:-runs/soak}"
read -r -a drives <<< "${SOAK_DRIVES:-recordings/drives}"
niceness="${SOAK_NICE:-0}"
export SUPERFLOW_IOX_PREFIX="soak$$"
export RUST_LOG="${RUST_LOG:-info}"

cargo build --release --locked -p superflow-pipeline -p superflow-trainer
rm -rf "$out"
mkdir -p "$out"
bin=target/release

nice -n "$niceness" "$bin/superflow-pipeline" --mcap "${drives[@]}" --run soak \
    --world-size 2 --batch-size 2 2> "$out/pipeline.log" &
pipeline=$!
trainers=()
for rank in 0 1; do
    nice -n "$niceness" "$bin/superflow-trainer" --run soak --rank "$rank" --world-size 2 \
        --unet tiny --vit tiny --pixel-stride 4 --steps 100000000 --checkpoint-every 200 \
        --out "$out/rank$rank" 2> "$out/rank$rank.log" &
    trainers+=($!)
done
# Trainers first (SIGTERM: the step in progress, a checkpoint, a clean exit), then the
# pipeline (SIGTERM: the batch in flight, then its shared memory is released).
stop() {
    kill -TERM "${trainers[@]}" 2>/dev/null || true
    for pid in "${trainers[@]}"; do wait "$pid" 2>/dev/null || true; done
    kill -TERM "$pipeline" 2>/dev/null || true
    wait "$pipeline" 2>/dev/null || true
}
trap stop EXIT

rss_kib() { awk '/^VmRSS:/ { print $2 }' "/proc/$1/status" 2>/dev/null || echo 0; }
# Pages actually held by this run's shared memory (tmpfs blocks, not the reserved size);
# 0 before the pipeline has created any (du then fails on the unmatched glob, and
# pipefail would turn that into a failure of the whole script) or while files vanish.
shm_kib() {
    { du -sk /dev/shm/"$SUPERFLOW_IOX_PREFIX"_* 2>/dev/null || true; } |
        awk '{ s += $1 } END { print s + 0 }'
}
steps() { grep -c '}$' "$out/rank$1/metrics.jsonl" 2>/dev/null || echo 0; }

echo "minute,pipeline_kib,rank0_kib,rank1_kib,shm_kib,rank0_steps,rank1_steps" > "$out/rss.csv"
echo "soak: $minutes min, peaks every $interval s -> $out/rss.csv"
start=$(date +%s)
end=$((start + minutes * 60))
next=$start
declare -a peak=(0 0 0 0)
while :; do
    now=$(date +%s)
    pids=("$pipeline" "${trainers[@]}")
    for k in 0 1 2; do
        kill -0 "${pids[$k]}" 2>/dev/null || { echo "process ${pids[$k]} died; see $out/*.log" >&2; exit 1; }
        v=$(rss_kib "${pids[$k]}")
        [ "$v" -le "${peak[$k]}" ] || peak[k]=$v
    done
    v=$(shm_kib)
    [ "$v" -le "${peak[3]}" ] || peak[3]=$v
    if [ "$now" -ge "$next" ]; then
        minute=$(awk -v s=$((now - start)) 'BEGIN { printf "%.2f", s / 60 }')
        line="$minute,${peak[0]},${peak[1]},${peak[2]},${peak[3]},$(steps 0),$(steps 1)"
        echo "$line" >> "$out/rss.csv"
        echo "  $line"
        peak=(0 0 0 0)
        next=$((next + interval))
        [ "$now" -lt "$end" ] || break
    fi
    sleep 5
done
stop
trap - EXIT
left=$(find /dev/shm -maxdepth 1 -name "${SUPERFLOW_IOX_PREFIX}_*" ! -name '*global_mgmt' | wc -l)
analyze "$out/rss.csv" "$left" | tee "$out/summary.txt"
