#!/usr/bin/env bash
# Issue 23 on the 16-core device (../shared/DEVICE.md): robots as a clique of peers against robots as
# clients of one router, same fleet, same host, one run each.  Writes $OUT/mesh-<shape>-<n>.json.
set -u
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --find-links .devwheels eclipse-zenoh==1.10.2 cryptography==50.0.2 jsonschema==4.26.0
export PYTHONPATH=$PWD
python3 -m scmr_mesh.imaging._aot > /dev/null 2>&1 || true
nproc; uptime
for spec in ${SPECS:-routers:128 clique:128 routers:256}; do
  shape=${spec%%:*}; n=${spec##*:}
  echo "== $shape $n robots"; uptime
  timeout ${STEP_S:-170} python3 -m scmr_mesh bench mesh --robots "$n" --duration 10 --workers 12 --capacity-seconds 0 \
    --crash-runs 0 --overload-robots 0 --shape "$shape" --json "$OUT/mesh-$shape-$n.json" \
    --run-dir "/tmp/bm-$shape-$n" > "$OUT/mesh-$shape-$n.log" 2>&1
  echo "exit $?"; tail -4 "$OUT/mesh-$shape-$n.log"
done
uptime
