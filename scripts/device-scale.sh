#!/usr/bin/env bash
# Issue 23 on the 16-core device (../shared/DEVICE.md), one call, every step bounded by `timeout` so a
# step that hangs leaves the others' results in $OUT:
#   mesh256   scmr bench mesh --robots 256 (the bench's own way of playing robots: swarms of 16), 12
#             workers, with the real pipeline's closed-loop capacity and the ingress ramp at 16 x 5 ms;
#   scale     scmr bench scale --quick --pipeline: 1, 2, 4 cloud nodes with the real pipeline sharing a
#             PostgreSQL server this script unpacks (.devwheels/pgdev.tar.xz: Debian 12's PostgreSQL 15
#             programs, the libraries they need in /opt/pglibs, wrappers in /opt/pgw/bin);
#   mesh64p2  the 2-core target beside it: taskset -c 0,1, 64 robots, 2 workers.
# Here, first: the wheels (DEVICE.md) and pgdev.tar.xz (scripts/device-pg-bundle.sh) into .devwheels/; then
#   carry [".devwheels"], command "bash scripts/device-scale.sh".
set -u
cd "$(dirname "$0")/.."
exec 3>&1
log() { echo "[$(date +%T) load $(cut -d' ' -f1 /proc/loadavg)] $*" >&3; }
{
  nproc; uptime; grep -m1 "model name" /proc/cpuinfo
  python3 -m pip install -q --no-index --find-links .devwheels eclipse-zenoh==1.10.2 cryptography==50.0.2 \
    jsonschema==4.26.0 "psycopg[binary]==3.3.9" 2>&1 | tail -3
  if [ -f .devwheels/pgdev.tar.xz ] && ! command -v initdb >/dev/null; then
    tar -xJf .devwheels/pgdev.tar.xz -C / && echo "PostgreSQL unpacked"
  fi
  python3 -m compileall -q scmr_mesh > /dev/null
  python3 -m scmr_mesh.imaging._aot 2>&1 | tail -1
} > "$OUT/setup.log" 2>&1
export PYTHONPATH=$PWD PATH=/opt/pgw/bin:$PATH PYTHONUNBUFFERED=1
log "setup done: $(tail -2 "$OUT/setup.log" | tr '\n' ' ')"

step() {  # name timeout command...
  local name=$1 t=$2; shift 2
  log "== $name: $*"
  timeout "$t" "$@" > "$OUT/$name.log" 2>&1
  log "exit $? ($name)"; tail -${TAIL:-6} "$OUT/$name.log" >&3
}

step mesh256 ${T256:-200} python3 -m scmr_mesh bench mesh --robots 256 --duration 10 --workers 12 \
  --capacity-seconds 5 --ingress-seconds 2 --ingress-workers 16 --ingress-service-ms 5 \
  --crash-runs 0 --overload-robots 0 --hogs 0 --json "$OUT/mesh256.json" --run-dir /tmp/bm256
step scale ${TSCALE:-170} python3 -m scmr_mesh bench scale --quick --pipeline --workers 1 --robots 32 \
  --duration 10 --json "$OUT/scale.json" --run-dir /tmp/bscale
step mesh64p2 ${T64:-130} taskset -c 0,1 python3 -m scmr_mesh bench mesh --robots 64 --duration 10 --workers 2 \
  --capacity-seconds 5 --ingress-seconds 0 --crash-runs 0 --overload-robots 0 --hogs 0 \
  --json "$OUT/mesh64p2.json" --run-dir /tmp/bm64
log "done"
