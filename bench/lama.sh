#!/usr/bin/env bash
# Build IRIS LaMa and our CARMEN driver for it once, into a cache, and print the driver's path (bench/run --peers lama).
#
#   bench/lama.sh [SRC]
#
# SRC (or $LAMA_SRC): an iris_lama tree (github iris-ua/iris_lama, BSD-3; measured at fd60e55, v1.3.1) or the bare
# git directory the search tool's fetch brings (/work/.mirror/iris-ua+iris_lama/repo), unpacked here at its HEAD.
# LaMa's code never enters this repository: the build and the driver are ../shared/peers/lama's build.sh and
# driver.cpp (or $LAMA_PEER_DIR), the products go to $LAMA_CACHE (default $TMPDIR/carto-bench-lama).
# A cached driver is reused, without SRC too, unless driver.cpp is newer than it; delete the cache to rebuild.
# Stdout: the driver's path, nothing else (build.sh's own output goes to stderr). Needs cmake, g++,
# libeigen3-dev and zlib1g-dev.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
peer=${LAMA_PEER_DIR:-$root/../shared/peers/lama}
cache=${LAMA_CACHE:-${TMPDIR:-/tmp}/carto-bench-lama}
driver=$cache/lama_driver
src=${1:-${LAMA_SRC:-}}
[ -f "$peer/build.sh" ] && [ -f "$peer/driver.cpp" ] || { echo "$0: no build.sh and driver.cpp in $peer" >&2; exit 2; }
if [ -x "$driver" ] && [ ! "$peer/driver.cpp" -nt "$driver" ]; then
    echo "$driver"
    exit 0
fi
[ -n "$src" ] || { echo "$0: no LaMa source: pass an iris_lama tree or its bare git directory, or set LAMA_SRC" >&2; exit 2; }
[ -d "$src" ] || { echo "$0: no such directory: $src" >&2; exit 2; }
mkdir -p "$cache"
if [ ! -f "$src/CMakeLists.txt" ] && git --git-dir="$src" rev-parse --verify -q HEAD >/dev/null 2>&1; then
    rm -rf "$cache/src" && mkdir -p "$cache/src"
    git --git-dir="$src" archive HEAD | tar -x -C "$cache/src"
    desc="iris_lama $(git --git-dir="$src" rev-parse --short HEAD)"
    src=$cache/src
else
    [ -f "$src/CMakeLists.txt" ] || { echo "$0: $src is neither an iris_lama tree nor a git directory" >&2; exit 2; }
    desc="iris_lama $(git -C "$src" rev-parse --short HEAD 2>/dev/null || echo "tree $src")"
fi
# A build dir left from another source makes cmake refuse it; a rebuild is rare enough to start clean.
rm -rf "$cache/build" "$cache/install"
# A half-built driver from an interrupted build must not count as built: build.sh writes it last, we move it in.
LAMA_SRC=$src LAMA_BUILD=$cache/build LAMA_PREFIX=$cache/install LAMA_DRIVER=$driver.tmp bash "$peer/build.sh" >&2
mv "$driver.tmp" "$driver"
echo "$desc" > "$cache/source.txt"
echo "$driver"
