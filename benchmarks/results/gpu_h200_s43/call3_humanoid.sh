#!/bin/bash
# Call 3 of 3 (carry .gpuC): join Warp, then Humanoid at the paper's sizes: one actor gradient of
# D.Va and of visual SHAC (Table 1 / Fig 10: 32 envs × 32 steps, 84²), each row printed as it
# finishes; then, with the time left, D.Va's paper-preset iteration (64 envs × 32 steps).
G=/tmp/g; T0=$SECONDS; LIMIT=${1:-540}
cat $G/w0 $G/w1 .gpuC/w2 | python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer)" > $G/gsite/warp/bin/warp.so || exit 1
export PYTHONPATH=$G/gpinned:$G/gsite:$PWD/src PYTHONUNBUFFERED=1 DVA_CACHE_DIR=/tmp/dvacache WARP_CACHE_PATH=/tmp/warpcache
nvidia-smi --query-gpu=name,memory.total,clocks.max.sm --format=csv,noheader | tee $OUT/gpu.txt
left() { echo $(( LIMIT - (SECONDS - T0) )); }
echo "=== cost ($(left) s left)"
timeout $(left) python3 benchmarks/results/gpu_h200_s43/cost_rows.py $OUT 2>&1 | grep -v "it/s\]" | tee $OUT/cost_log.txt
echo "cost done after $((SECONDS-T0)) s"
t=$(left); [ $t -gt 60 ] && timeout $t python3 benchmarks/iteration.py --task humanoid --preset paper > $OUT/iteration_humanoid.txt 2>&1
echo "iteration rc $? after $((SECONDS-T0)) s"; tail -20 $OUT/iteration_humanoid.txt 2>/dev/null
