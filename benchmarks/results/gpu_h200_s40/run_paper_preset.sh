#!/bin/bash
# Call 2 of 2: finish Warp, then D.Va's paper preset on Hopper and Humanoid: s / iteration, backward and memory.
G=/tmp/g; T0=$SECONDS; LIMIT=${LIMIT:-500}
[ -d $G/warp_py ] && mv $G/warp_py $G/gsite/warp
cat $G/warp.so.xz.part0 .gpu2/warp.so.xz.part1 | python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer)" > $G/gsite/warp/bin/warp.so || exit 1
if [ "$(cat $G/choice)" = pinned ]; then export PYTHONPATH=$G/gpinned:$G/gsite:$PWD/src; else export PYTHONPATH=$G/gsite:$PWD/src; fi
export PYTHONUNBUFFERED=1 DVA_CACHE_DIR=/tmp/dvacache
nvidia-smi --query-gpu=name,memory.total,clocks.max.sm --format=csv,noheader | tee $OUT/gpu.txt
python3 -c "import warp as wp; wp.init(); print('warp', wp.__version__, wp.get_cuda_devices())" 2>&1 | tail -3
left() { echo $(( LIMIT - (SECONDS - T0) )); }
step() { local name=$1; shift; local t=$(left); [ $t -gt 20 ] || { echo "skip $name"; return; }
  echo "=== $name ($t s left)"; timeout $t "$@" > $OUT/$name.txt 2>&1; echo "rc $? after $((SECONDS-T0)) s"; tail -25 $OUT/$name.txt; }
step iteration_hopper python3 benchmarks/iteration.py --task hopper --preset paper
step cost_hopper python3 -m dva.cli analyze cost --tasks hopper --out $OUT/hopper
step iteration_humanoid python3 benchmarks/iteration.py --task humanoid --preset paper
step cost_humanoid python3 -m dva.cli analyze cost --tasks humanoid --out $OUT/humanoid
