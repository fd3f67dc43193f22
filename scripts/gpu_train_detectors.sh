#!/bin/bash
# One GPU-machine session, as run on an NVIDIA H200 on 2026-12-04 from the repository root (after
# `python scripts/gpu_subset.py device_data` on a machine with ../shared/data, the folder carried along): the
# network-speed-gpu bench row, then the detector ablation (none / se / cbam / esea from scratch, one recipe) and
# round 5 of the shipped detector, all five at once, their iteration count set from a short calibration so that
# they end before DEADLINE seconds (that day: 3600). Weights land in models/detector_<a>_gpu.pt and $OUT.
set -u
OUT=${OUT:-runs/gpu_out}; mkdir -p "$OUT"
DEV=${DEV:-cuda}; BATCH=${BATCH:-32}; DEADLINE=${DEADLINE:-480}; WORKERS=${WORKERS:-2}; CAL=${CAL:-150}; MAXIT=${MAXIT:-30000}
export VSLAM_DATA=${VSLAM_DATA:-$PWD/device_data} PYTHONPATH=$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
L=/tmp/gpulogs; rm -rf $L /tmp/cal /tmp/tr; mkdir -p $L
(nvidia-smi -L; nproc; free -g | head -2; python3 -c "import torch, cv2, numpy; print(torch.__version__, cv2.__version__, numpy.__version__, torch.cuda.is_available())") 2>&1 | tee $L/env.txt
if [ "$DEV" = cuda ]; then
  timeout 120 python3 -m vslam.cli bench --only network-speed-gpu --jobs 1 --runs /tmp/bench > $L/bench.log 2>&1
  echo "bench rc=$? at $(el)s"; tail -3 $L/bench.log; grep -A4 "^| row | device" BENCHMARKS.md
  cp BENCHMARKS.json BENCHMARKS.md $OUT/
fi
run() {  # name, iterations, out root, extra --set ...
  local a=$1 n=$2 root=$3; shift 3
  python3 -m vslam.cli train detector -c configs/train_detector.yaml -o $root/$a --device $DEV --set iterations=$n \
    --set batch=$BATCH --set workers=$WORKERS --set threads=1 --set evaluate=false --set log_every=10 --set ckpt_every=500 \
    --set weights=models/detector_${a}_gpu.pt "$@" \
    > $root/$a.log 2>&1
}
variants() {  # iterations, out root
  for a in none se cbam esea; do run $a $1 $2 --set attention=$a & done
  run esea_r5 $1 $2 --set attention=esea --set lr=0.0007 --set warmup=50 --set seed=5 --set paste_closeup=0.15 \
    --set init=models/detector_esea.pt &
  wait
}
mkdir -p /tmp/cal /tmp/tr
variants $CAL /tmp/cal
rm -f models/detector_*_gpu.pt
echo "calibration done at $(el)s"
N=$(python3 - $CAL $DEADLINE $T0 $MAXIT <<'PY'
import csv, sys, time, glob
cal, deadline, t0, cap = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
rates = []
for f in sorted(glob.glob("/tmp/cal/*/log.csv")):
    rows = {int(r["iteration"]): float(r["seconds"]) for r in csv.DictReader(open(f))}
    a, b = min(k for k in rows if k >= cal // 3), max(rows)
    rates.append((b - a) / max(1, rows[b] - rows[a]))
    print(f, f"{rates[-1]:.2f} it/s", file=sys.stderr)
budget = deadline - (time.time() - t0) - 45  # start-up of the runs, precise BN, saving
n = int(min(rates) * budget * 0.9) // 100 * 100
print(max(100, min(cap, n)))
PY
)
[ -n "$N" ] || N=3000  # calibration failed: a guess
echo "iterations per run: $N (at $(el)s)"
variants $N /tmp/tr
echo "training done at $(el)s"
for a in none se cbam esea esea_r5; do
  tail -1 /tmp/tr/$a/log.csv; cp models/detector_${a}_gpu.pt $OUT/ || echo "no model for $a"
done
cp -r /tmp/cal $L/cal_logs; for a in none se cbam esea esea_r5; do mkdir -p $L/tr/$a; cp /tmp/tr/$a.log /tmp/tr/$a/log.csv $L/tr/$a/ 2>/dev/null; done
rm -f $L/cal_logs/*/last.pt $L/cal_logs/*/model.pt
tar czf $OUT/logs.tgz -C /tmp gpulogs
echo "end at $(el)s"; ls -la $OUT
