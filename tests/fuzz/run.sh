#!/usr/bin/env bash
# Runs each fuzz target of tests/fuzz for a bounded time, starting from the committed
# corpus (tests/fuzz/corpus/<target>/), and fails if any target crashes.
#
# Needs: rustup with a nightly toolchain (`rustup toolchain install nightly`), a C/C++
# compiler (libfuzzer-sys builds libFuzzer), and cargo-fuzz (installed here with
# `cargo install cargo-fuzz --locked` when missing). Run from anywhere.
#
#   tests/fuzz/run.sh [SECONDS_PER_TARGET] [--update-corpus]     (default 300 s)
#
# New inputs go to tests/fuzz/scratch/<target>/ (ignored by git); --update-corpus merges
# them into the committed corpus afterwards (`cargo fuzz cmin`). A crash leaves its input
# in tests/fuzz/artifacts/<target>/ and the log in tests/fuzz/scratch/<target>.log.
# Environment: TARGETS (default: every target), SANITIZER (none | address; default
# none, ~2x faster, the code is safe Rust), TIMEOUT (seconds per input, default 10),
# RSS_LIMIT_MB (default 2048). Builds have debug assertions on (overflow checks).
set -euo pipefail

seconds=300
update=0
for arg in "$@"; do
    case "$arg" in
        --update-corpus) update=1 ;;
        ''|*[!0-9]*) echo "usage: $0 [SECONDS_PER_TARGET] [--update-corpus]" >&2; exit 2 ;;
        *) seconds="$arg" ;;
    esac
done

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$root"
fuzz_dir=tests/fuzz
targets="${TARGETS:-mcap_drive message_decoders batch_reader}"
sanitizer="${SANITIZER:-none}"
timeout="${TIMEOUT:-10}"
rss="${RSS_LIMIT_MB:-2048}"

if ! cargo +nightly --version >/dev/null 2>&1; then
    echo "error: no nightly toolchain (rustup toolchain install nightly)" >&2
    exit 2
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "cargo-fuzz missing: installing it" >&2
    cargo install cargo-fuzz --locked
fi

build=(cargo +nightly fuzz build --fuzz-dir "$fuzz_dir" --sanitizer "$sanitizer" --debug-assertions)
echo "== building: ${build[*]}"
"${build[@]}"

# Per-input files of mcap_drive go here, removed at the end.
export SUPERFLOW_FUZZ_SCRATCH
SUPERFLOW_FUZZ_SCRATCH="$(mktemp -d "${TMPDIR:-/tmp}/superflow-fuzz.XXXXXX")"
if [ -d /dev/shm ] && [ -w /dev/shm ]; then
    rmdir "$SUPERFLOW_FUZZ_SCRATCH"
    SUPERFLOW_FUZZ_SCRATCH="$(mktemp -d /dev/shm/superflow-fuzz.XXXXXX)"
fi
trap 'rm -rf "$SUPERFLOW_FUZZ_SCRATCH"' EXIT

summary=()
failed=0
for target in $targets; do
    scratch="$fuzz_dir/scratch/$target"
    artifacts="$fuzz_dir/artifacts/$target"
    log="$fuzz_dir/scratch/$target.log"
    mkdir -p "$scratch" "$artifacts"
    before="$(find "$artifacts" -type f | sort)"
    echo "== $target: ${seconds}s (log $log)"
    dict=()
    case "$target" in
        mcap_drive|message_decoders) dict=(-dict="$fuzz_dir/decoders.dict") ;;
    esac
    set +e
    # The first corpus directory receives new inputs; the committed one is only read.
    cargo +nightly fuzz run --fuzz-dir "$fuzz_dir" --sanitizer "$sanitizer" --debug-assertions \
        "$target" "$scratch" "$fuzz_dir/corpus/$target" -- \
        -max_total_time="$seconds" -timeout="$timeout" -rss_limit_mb="$rss" \
        -print_final_stats=1 "${dict[@]}" >"$log" 2>&1
    rc=$?
    set -e
    execs="$(grep -oE 'stat::number_of_executed_units: *[0-9]+' "$log" | tail -1 | grep -oE '[0-9]+$' || true)"
    rss_peak="$(grep -oE 'stat::peak_rss_mb: *[0-9]+' "$log" | tail -1 | grep -oE '[0-9]+$' || true)"
    last="$(grep -E '^#[0-9]+' "$log" | tail -1 || true)"
    cov="$(echo "$last" | grep -o 'cov: [0-9]*' | grep -o '[0-9]*' || true)"
    ft="$(echo "$last" | grep -o 'ft: [0-9]*' | grep -o '[0-9]*' || true)"
    corp="$(echo "$last" | grep -o 'corp: [0-9]*/[0-9]*[a-zA-Z]*' | cut -d' ' -f2 || true)"
    new_artifacts="$(comm -13 <(echo "$before") <(find "$artifacts" -type f | sort) | grep . || true)"
    crashes="$(echo -n "$new_artifacts" | grep -c . || true)"
    if [ "$rc" -ne 0 ] || [ "$crashes" -ne 0 ]; then
        failed=1
        echo "!! $target: exit $rc, new artifacts:" >&2
        echo "$new_artifacts" | sed 's/^/   /' >&2
        grep -E -m1 -A12 '^==[0-9]+==|panicked at|ERROR: libFuzzer' "$log" >&2 || tail -30 "$log" >&2
    fi
    summary+=("$(printf '%-18s %6ss  execs %-10s cov %-6s ft %-7s corpus %-12s peak_rss_mb %-6s crashes %s' \
        "$target" "$seconds" "${execs:-?}" "${cov:-?}" "${ft:-?}" "${corp:-?}" "${rss_peak:-?}" "$crashes")")
    if [ "$update" -eq 1 ] && [ "$rc" -eq 0 ]; then
        echo "== $target: merging new inputs into $fuzz_dir/corpus/$target"
        cp -n "$scratch"/* "$fuzz_dir/corpus/$target/" 2>/dev/null || true
        cargo +nightly fuzz cmin --fuzz-dir "$fuzz_dir" --sanitizer "$sanitizer" --debug-assertions \
            "$target" "$fuzz_dir/corpus/$target" >>"$log" 2>&1
    fi
done

echo "== summary (${seconds}s per target)"
printf '%s\n' "${summary[@]}"
if [ "$failed" -ne 0 ]; then
    echo "FAILED: a target crashed; reproduce with" >&2
    echo "  cargo +nightly fuzz run --fuzz-dir $fuzz_dir --sanitizer $sanitizer --debug-assertions <target> <artifact>" >&2
    exit 1
fi
