#!/usr/bin/env bash
# OpenSLAM GMapping beside carto on one bench case, for side-by-side wall times (docs/gmapping.md).
#
#   bench/openslam_gmapping.sh SRC CASE [PARTICLES]
#
# SRC: a checkout of https://github.com/ros-perception/openslam_gmapping (measured at 5105476).
# CASE: a directory of ../shared/data/bench (intel, orebro, ...). Builds the gfs_nogui driver with g++ -O3
# into a temporary directory (two changes, for the measurement only: a stray "<< cout" that g++ 12 rejects,
# and a 20 ms sleep in the driver's event loop, which otherwise spins on the second core), runs it with
# ROS slam_gmapping's parameters and every scan processed, prints its wall time and peak RSS, then runs
# carto's bench on the same case with the same particle count.
set -euo pipefail
src=${1:?usage: $0 SRC CASE [PARTICLES]}
case=${2:?usage: $0 SRC CASE [PARTICLES]}
particles=${3:-30}
root=$(cd "$(dirname "$0")/.." && pwd)
data=$root/../shared/data/bench/$case
[ -f "$data/scans.clf.gz" ] || { echo "$0: no $data/scans.clf.gz" >&2; exit 2; }
[ -f "$src/gui/gfs_nogui.cpp" ] || { echo "$0: $src is not an openslam_gmapping checkout (no gui/gfs_nogui.cpp)" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cp -r "$src"/. "$work/src"
cd "$work/src"
sed -i 's/<< cout << " xmin="/<< " xmin="/' gui/gsp_thread.cpp
sed -i 's/^\(\s*\)while (!done){/\1while (!done){ usleep(20000);/' gui/gfs_nogui.cpp
grep -rhoE "gmapping/[a-z_/]*_export.h" include | sort -u | while read -r h; do
    mkdir -p "gen/$(dirname "$h")"
    n=$(basename "$h" _export.h | tr a-z A-Z)
    printf '#pragma once\n#define %s_EXPORT\n#define %s_NO_EXPORT\n' "$n" "$n" > "gen/$h"
done
g++ -O3 -DNDEBUG -w -Iinclude -Igen -o "$work/gfs_nogui" \
    utils/stat.cpp utils/movement.cpp sensor/sensor_base/*.cpp sensor/sensor_odometry/*.cpp \
    sensor/sensor_range/*.cpp log/configuration.cpp log/carmenconfiguration.cpp log/sensorlog.cpp \
    log/sensorstream.cpp configfile/configfile.cpp scanmatcher/smmap.cpp scanmatcher/scanmatcher.cpp \
    scanmatcher/scanmatcherprocessor.cpp scanmatcher/eig3.cpp gridfastslam/gridslamprocessor_tree.cpp \
    gridfastslam/motionmodel.cpp gridfastslam/gridslamprocessor.cpp gridfastslam/gfsreader.cpp \
    gui/gsp_thread.cpp gui/gfs_nogui.cpp -lpthread
zcat "$data/scans.clf.gz" > "$work/scans.clf"
cd "$work"
echo "== OpenSLAM GMapping, $case, $particles particles, every scan"
/usr/bin/time -o time.txt -f "wall %e s, peak RSS %M KB" ./gfs_nogui -filename scans.clf -outfilename out.gfs \
    -particles "$particles" -delta 0.05 -maxrange 80 -maxUrange 80 -sigma 0.05 -kernelSize 1 -lstep 0.05 \
    -astep 0.05 -iterations 5 -lsigma 0.075 -lobsGain 3.0 -lskip 0 -srr 0.1 -srt 0.2 -str 0.1 -stt 0.2 \
    -resampleThreshold 0.5 -llsamplerange 0.01 -llsamplestep 0.01 -lasamplerange 0.005 -lasamplestep 0.005 \
    -xmin -100 -xmax 100 -ymin -100 -ymax 100 -linearUpdate 0 -angularUpdate 0 > gfs.log 2>&1
cat time.txt
echo "== carto gmapping, $case, $particles particles"
cd "$root"
bench/run --algorithm gmapping --set "gmapping.particles=$particles" --cases "$case" --results "$work/carto" \
    --no-doc | grep -E "^== .*:"
