#!/usr/bin/env bash
# Run the whole test suite N times (default 3) with two CPU-bound processes beside it, as a loaded
# 2-core CI machine would; print each run's result line and wall time, and a summary.  The hogs are
# killed however the script ends.  Extra arguments after N go to pytest (e.g. -x, -k EXPR).
#
#   bash scripts/suite-under-load.sh [N] [pytest args...]
#
# Exit status: 0 when every run passed, 1 otherwise.  Each run's full output is kept in
# test-artifacts/suite-under-load/run-<i>.log.
set -uo pipefail
cd "$(dirname "$0")/.."

runs=${1:-3}
shift || true
if ! [[ "$runs" =~ ^[1-9][0-9]*$ ]]; then
    echo "suite-under-load: N must be a positive whole number of runs, got '$runs'" >&2
    exit 2
fi
python=.venv/bin/python
if [ ! -x "$python" ]; then
    echo "suite-under-load: $python is missing: run 'bash scripts/install.sh' first" >&2
    exit 2
fi
logs=test-artifacts/suite-under-load
mkdir -p "$logs"

hogs=()
stop_hogs() {
    for pid in "${hogs[@]}"; do
        kill "$pid" 2>/dev/null
        wait "$pid" 2>/dev/null
    done
    hogs=()
}
trap stop_hogs EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

for _ in 1 2; do
    python3 -c 'while True: pass' &
    hogs+=("$!")
done
echo "two CPU hogs running (pids ${hogs[*]}); load average: $(cut -d' ' -f1-3 /proc/loadavg)"

failed=0
for i in $(seq 1 "$runs"); do
    start=$(date +%s)
    "$python" -m pytest -q -p no:cacheprovider "$@" > "$logs/run-$i.log" 2>&1
    code=$?
    secs=$(( $(date +%s) - start ))
    result=$(grep -E '^(=+ )?[0-9]+ (passed|failed|error)' "$logs/run-$i.log" | tail -1 | sed 's/=//g; s/^ *//; s/ *$//')
    [ "$code" -eq 0 ] || failed=$((failed + 1))
    printf 'run %d/%d: exit %d, %dm%02ds, %s (load average %s)\n' "$i" "$runs" "$code" $((secs / 60)) $((secs % 60)) \
        "${result:-no result line, see $logs/run-$i.log}" "$(cut -d' ' -f1-3 /proc/loadavg)"
done
echo "$((runs - failed)) of $runs runs passed"
[ "$failed" -eq 0 ]
