#!/usr/bin/env bash
# One bounded libFuzzer run (ctest's fuzz_<name>): BINARY CORPUS REGRESSIONS ARTIFACTS LOG.
# KESTREL_FUZZ_SECONDS (default 30) bounds it; new inputs go into CORPUS,
# REGRESSIONS (if present) is read too, a crash is written to ARTIFACTS/<name>-crash-*
# (replay it with fuzz_<name>_corpus replay FILE; it becomes a file in
# tests/fuzz/regressions/<name>/). The run's statistics end the log and the output.
set -uo pipefail
bin=$1 corpus=$2 reg=$3 artifacts=$4 log=$5
name=$(basename "$bin")
mkdir -p "$corpus" "$artifacts" "$(dirname "$log")"
dirs=("$corpus")
[ -d "$reg" ] && dirs+=("$reg")
# detect_leaks stays on; -timeout: one input taking 25 s is a hang, a finding.
"$bin" -max_total_time="${KESTREL_FUZZ_SECONDS:-30}" -rss_limit_mb=2048 -timeout=25 -print_final_stats=1 \
  -artifact_prefix="$artifacts/$name-" "${dirs[@]}" >"$log" 2>&1
rc=$?
grep -E '^(stat::number_of_executed_units|stat::average_exec_per_sec|stat::new_units_added|stat::peak_rss_mb)' "$log" \
  | sed "s/^/$name /"
echo "$name corpus: $(find "$corpus" -type f | wc -l) inputs"
if [ $rc -ne 0 ]; then
  echo "$name: FAILED (exit $rc); the end of $log:" >&2
  tail -n 60 "$log" >&2
fi
exit $rc
