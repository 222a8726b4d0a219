#!/bin/sh
# Installs this build into a temporary prefix and builds docs/api.md's example
# against it as a separate project, twice: through find_package(Kestrel) and
# its imported targets, and through pkg-config. Both programs replay a
# simulated log (made by the installed `kestrel`) and must print the same
# trajectory. Usage: test_install.sh BUILD_DIR API_EXAMPLE_CPP WORK_DIR
set -eu
build="$1"
example="$2"
work="$3"
rm -rf "$work"
mkdir -p "$work/app"
trap 'rm -rf "$work"' EXIT
prefix="$work/prefix"

echo "== cmake --install $build --prefix $prefix"
cmake --install "$build" --prefix "$prefix" >"$work/install.log"
for f in bin/kestrel include/kestrel/core/kestrel.hpp include/kestrel/drivers/open_log.hpp include/kestrel/msgs.hpp \
         include/kestrel/rt/spsc_ring.hpp; do
  test -f "$prefix/$f" || { echo "FAIL: $f not installed"; exit 1; }
done
cfg=$(find "$prefix" -name KestrelConfig.cmake)
pc=$(find "$prefix" -name kestrel.pc)
test -n "$cfg" || { echo "FAIL: no KestrelConfig.cmake"; exit 1; }
test -n "$pc" || { echo "FAIL: no kestrel.pc"; exit 1; }
# Nothing installed may point back into the source or build tree.
src=$(cd "$(dirname "$0")/../.." && pwd)
if grep -rl -e "$src" -e "$build" "$(dirname "$cfg")" "$pc"; then echo "FAIL: the installed package names the build tree"; exit 1; fi
if find "$prefix/include" -name '*.cpp' | grep -q .; then echo "FAIL: sources installed as headers"; exit 1; fi

echo "== find_package(Kestrel) project"
cp "$example" "$work/app/main.cpp"
cat >"$work/app/CMakeLists.txt" <<'CMAKE'
cmake_minimum_required(VERSION 3.22)
project(kestrel_consumer CXX)
set(CMAKE_CXX_STANDARD 17)
find_package(Kestrel 0.1 REQUIRED)
add_executable(my_app main.cpp)
target_link_libraries(my_app Kestrel::kestrel_core Kestrel::kestrel_drivers)
CMAKE
cmake -S "$work/app" -B "$work/app/build" -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$prefix" >"$work/configure.log" ||
  { cat "$work/configure.log"; exit 1; }
cmake --build "$work/app/build" >"$work/build.log" 2>&1 || { tail -40 "$work/build.log"; exit 1; }

echo "== pkg-config kestrel"
flags=$(PKG_CONFIG_PATH="$(dirname "$pc")" pkg-config --cflags --libs kestrel)
echo "$flags" | head -c 400; echo
c++ -O2 "$work/app/main.cpp" -o "$work/my_app_pc" $flags >"$work/pc_build.log" 2>&1 || { tail -40 "$work/pc_build.log"; exit 1; }

echo "== run both on a simulated log"
"$prefix/bin/kestrel" version
"$prefix/bin/kestrel" version | grep -q "^drivers: " || { echo "FAIL: kestrel version lists no drivers"; exit 1; }
"$prefix/bin/kestrel" sim --scenario hover --duration 4 --seed 5 --width 160 --height 120 --out "$work/hover.klog" >/dev/null
"$work/app/build/my_app" "$work/hover.klog" vo >"$work/traj_cmake.txt"
"$work/my_app_pc" "$work/hover.klog" vo >"$work/traj_pc.txt"
n=$(wc -l <"$work/traj_cmake.txt")
echo "trajectory: $n poses"
test "$n" -ge 60 || { echo "FAIL: only $n poses"; exit 1; }
cmp "$work/traj_cmake.txt" "$work/traj_pc.txt" || { echo "FAIL: the two builds disagree"; exit 1; }
echo "PASS"
