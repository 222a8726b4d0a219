#!/bin/sh
# The Python contract of issue 47: after `cmake --install BUILD --prefix P`,
# PYTHONPATH=P/lib/python3/dist-packages python3 -c "import kestrel; kestrel.replay(LOG)"
# returns an (N, 8) array. The module must come from the prefix, not the build
# tree, and must work with the build tree out of sight.
# Usage: test_install.sh BUILD_DIR PYTHON WORK_DIR
set -eu
build="$1"
python="$2"
work="$3"
rm -rf "$work"
mkdir -p "$work"
trap 'rm -rf "$work"' EXIT
prefix="$work/prefix"
cmake --install "$build" --prefix "$prefix" >"$work/install.log"
site="$prefix/lib/python3/dist-packages"
test -f "$site/kestrel/__init__.py" || { echo "FAIL: no kestrel/__init__.py under $site"; exit 1; }
ls "$site"/kestrel/_kestrel*.so >/dev/null 2>&1 || { echo "FAIL: no extension module under $site/kestrel"; exit 1; }
"$prefix/bin/kestrel" sim --scenario hover --duration 4 --seed 5 --width 160 --height 120 --out "$work/hover.klog" >/dev/null
cd "$work"
out=$(env -u KESTREL_BIN_DIR PYTHONPATH="$site" "$python" -c "
import kestrel
a = kestrel.replay('$work/hover.klog')
print(kestrel.__file__)
print(type(a).__module__, a.dtype, a.shape)
") || { echo "FAIL: import kestrel / replay from the installed tree"; exit 1; }
echo "$out"
echo "$out" | head -1 | grep -q "^$site/kestrel/__init__.py" || { echo "FAIL: kestrel imported from elsewhere"; exit 1; }
echo "$out" | tail -1 | grep -Eq "^numpy float64 \([0-9]+, 8\)$" || { echo "FAIL: replay did not return an (N, 8) array"; exit 1; }
n=$(echo "$out" | tail -1 | sed -E 's/.*\(([0-9]+), 8\)/\1/')
test "$n" -ge 60 || { echo "FAIL: only $n poses"; exit 1; }
echo "PASS"
