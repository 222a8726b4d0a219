# Sourced by test.sh and cross-aarch64.sh: `part NAME COMMAND...` runs one part
# of the script and records its wall time (a failure ends the run); on exit the
# parts and their times are printed, with which part failed. The sourcing script
# sets `script_name` first.
costs=()
t_all=$(date +%s)
report() {
  local rc=$?
  echo "== $script_name: wall time per part =="
  for c in "${costs[@]}"; do echo "  $c"; done
  printf '  %-34s %5d s\n' "total" $(( $(date +%s) - t_all ))
  [ $rc -eq 0 ] || echo "$script_name: FAILED (exit $rc) in the part after the last one listed"
}
trap report EXIT
part() {
  local name=$1 t0
  shift
  echo "== $name =="
  t0=$(date +%s)
  "$@"
  costs+=("$(printf '%-34s %5d s' "$name" $(( $(date +%s) - t0 )))")
}
