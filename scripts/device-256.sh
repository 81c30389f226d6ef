#!/usr/bin/env bash
# Issue 23, second device call: 256 robots twice (does a swarm's start-up hang recur? a swarm not
# ready at 80 s gets SIGABRT, so faulthandler writes every thread's stack to its log) with the cloud's
# CPU per thread over 8 s of the run (/proc/PID/task), then 128 robots if time is left.
set -u
cd "$(dirname "$0")/.."
T0=$(date +%s)
python3 -c "import zenoh, psycopg" 2>/dev/null || python3 -m pip install -q --no-index --find-links .devwheels \
  eclipse-zenoh==1.10.2 cryptography==50.0.2 jsonschema==4.26.0 "psycopg[binary]==3.3.9" > /dev/null 2>&1
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 PYTHONFAULTHANDLER=1
python3 -m compileall -q scmr_mesh > /dev/null; python3 -m scmr_mesh.imaging._aot 2>&1 | tail -1
snap() {  # per thread name: utime+stime ticks of process $1
  for t in /proc/$1/task/*; do n=$(tr ' ' _ < $t/comm 2>/dev/null); v=$(sed 's/.*) //' $t/stat 2>/dev/null | awk '{print $12+$13}'); [ -n "$v" ] && echo "$n $v"; done |
    awk '{a[$1]+=$2; c[$1]++} END{for(k in a) print k, c[k], a[k]}' | sort
}
one() {  # name robots
  local name=$1 n=$2 R=/tmp/$1/robots-$2 e=0
  echo "== $name: $n robots, load $(cut -d' ' -f1 /proc/loadavg), t+$(( $(date +%s) - T0 ))s"
  python3 -m scmr_mesh bench mesh --robots $n --duration ${DURATION:-10} --workers ${WORKERS:-12} --capacity-seconds 0 --ingress-seconds 0 \
    --crash-runs 0 --overload-robots 0 --hogs 0 ${SERVER_ARGS:-} --json $OUT/$name.json --run-dir /tmp/$name > /tmp/$name.log 2>&1 &
  local B=$! s0=$(date +%s)
  while kill -0 $B 2>/dev/null; do sleep 0.5; e=$(( $(date +%s) - s0 ))
    grep -q "robots ready" /tmp/$name.log && break; [ $e -ge ${ABORT_S:-80} ] && break; done
  if grep -q "robots ready" /tmp/$name.log; then
    echo "robots ready line after ${e}s"; sleep 1
    local pids=$(pgrep -f "ready/cloud.ready")  # the cloud, its data process, its workers
    for p in $pids; do snap $p > /tmp/a.$p; done; sleep 8; for p in $pids; do snap $p > /tmp/b.$p; done
    echo "cloud processes (pid: CPU s over 8 s by thread name, threads):"
    for p in $pids; do echo "  $p: $(join /tmp/a.$p /tmp/b.$p | awk '{d=($5-$3)/100; if (d>0.05) printf "%s %d %.2f; ", $1, $4, d}')"; done
  else
    echo "NOT READY after ${e}s: $(ls $R/ready | wc -l) ready files"
    for f in $R/logs/swarm-*.log; do s=$(basename $f .log); [ -e $R/ready/$s.ready ] && continue
      for p in $(pgrep -f "ready/$s.ready"); do echo "$s pid $p $(grep -E 'State|Threads' /proc/$p/status | tr '\n' ' ')"; kill -ABRT $p; done
      sleep 1; cp $f $OUT/ 2>/dev/null; done
  fi
  wait $B; echo "bench exit $?"; grep -v "liveliness\|data.queue" /tmp/$name.log | grep -E "robots:|CPU ms|^ +[0-9]+ +5 " | cut -c1-300
  grep -v "liveliness" /tmp/$name.log | tail -c 20000 > $OUT/$name.log
}
for spec in ${RUNS:-bm256a:256 bm256b:256 bm128:128}; do
  [ $(( $(date +%s) - T0 )) -lt ${UNTIL_S:-200} ] && one ${spec%%:*} ${spec##*:}
done
echo "done t+$(( $(date +%s) - T0 ))s"
