#!/usr/bin/env bash
# Soak: the pipeline streams to two trainers (shard mode, tiny presets) for a set time;
# the resident memory (RSS) of every process and the bytes in /dev/shm are recorded
# every interval, then a straight line is fitted to each process's RSS after the
# warm-up. Memory is flat when no process grows by more than max(5 % of its mean,
# 16 MiB) over the run (the fitted slope times the measured span); otherwise it exits 1.
# Not part of `cargo test`.
#
# Usage: tests/soak.sh [MINUTES]   (default 30)
#   SOAK_INTERVAL_SECS=60  sampling interval
#   SOAK_WARMUP_MINUTES=3  samples before this are not fitted (allocators and caches fill)
#   SOAK_DRIVES="recordings/drives"  what the pipeline streams
#   SOAK_OUT=runs/soak     rss.csv, summary.txt, the processes' logs and outputs
#   SOAK_NICE=0            niceness of the processes (e.g. 19 on a shared machine)
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="${1:-30}"
interval="${SOAK_INTERVAL_SECS:-60}"
warmup="${SOAK_WARMUP_MINUTES:-3}"
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
stop() {
    kill -KILL "${trainers[@]}" 2>/dev/null || true
    kill -TERM "$pipeline" 2>/dev/null || true
    wait "$pipeline" 2>/dev/null || true
}
trap stop EXIT

rss_kib() { awk '/^VmRSS:/ { print $2 }' "/proc/$1/status" 2>/dev/null || echo 0; }
shm_kib() { du -sk --apparent-size /dev/shm/"$SUPERFLOW_IOX_PREFIX"_* 2>/dev/null | awk '{ s += $1 } END { print s + 0 }'; }
steps() { grep -c '}$' "$out/rank$1/metrics.jsonl" 2>/dev/null || echo 0; }

echo "minute,pipeline_kib,rank0_kib,rank1_kib,shm_kib,rank0_steps,rank1_steps" > "$out/rss.csv"
echo "soak: $minutes min, a sample every $interval s -> $out/rss.csv"
start=$(date +%s)
end=$((start + minutes * 60))
while :; do
    now=$(date +%s)
    for pid in "$pipeline" "${trainers[@]}"; do
        kill -0 "$pid" 2>/dev/null || { echo "process $pid died; see $out/*.log" >&2; exit 1; }
    done
    minute=$(awk -v s=$((now - start)) 'BEGIN { printf "%.2f", s / 60 }')
    line="$minute,$(rss_kib "$pipeline"),$(rss_kib "${trainers[0]}"),$(rss_kib "${trainers[1]}"),$(shm_kib),$(steps 0),$(steps 1)"
    echo "$line" >> "$out/rss.csv"
    echo "  $line"
    [ "$now" -lt "$end" ] || break
    sleep $((interval < end - now ? interval : end - now))
done
stop
trap - EXIT
left=$(find /dev/shm -maxdepth 1 -name "${SUPERFLOW_IOX_PREFIX}_*" ! -name '*global_mgmt' | wc -l)

# Least-squares slope of each process's RSS after the warm-up.
awk -F, -v warmup="$warmup" -v left="$left" '
NR == 1 { for (i = 2; i <= 5; i++) name[i] = $i; next }
$1 >= warmup {
    n++; x = $1
    for (i = 2; i <= 5; i++) { y = $i / 1024; sx[i] += x; sy[i] += y; sxx[i] += x * x; sxy[i] += x * y
        if (n == 1 || y < lo[i]) lo[i] = y; if (n == 1 || y > hi[i]) hi[i] = y }
    if (n == 1) first = x; last = x
}
END {
    if (n < 3) { print "soak: fewer than 3 samples after the warm-up; run longer"; exit 1 }
    span = last - first; bad = 0
    printf "%-10s %10s %10s %10s %14s %14s %s\n", "process", "mean MiB", "min MiB", "max MiB", "slope MiB/h", "growth MiB", "verdict"
    for (i = 2; i <= 5; i++) {
        mean = sy[i] / n; d = n * sxx[i] - sx[i] * sx[i]
        slope = d > 0 ? (n * sxy[i] - sx[i] * sy[i]) / d : 0
        growth = slope * span; limit = mean * 0.05 > 16 ? mean * 0.05 : 16
        verdict = growth <= limit ? "flat" : "GROWS"; if (growth > limit) bad = 1
        printf "%-10s %10.1f %10.1f %10.1f %14.2f %14.2f %s (limit %.1f)\n", name[i], mean, lo[i], hi[i], slope * 60, growth, verdict, limit
    }
    printf "fitted %d samples over %.1f min after a %s min warm-up; files left in /dev/shm: %d\n", n, span, warmup, left
    if (left > 0) bad = 1
    exit bad
}' "$out/rss.csv" | tee "$out/summary.txt"
