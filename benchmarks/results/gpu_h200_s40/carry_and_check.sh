#!/bin/bash
# Call 1 of 2: unpack the carried packages into /tmp/g (kept while the machine stays warm) and check imports.
G=/tmp/g; mkdir -p $G
cp .gpu1/warp.so.xz.part0 $G/ && python3 -c "import tarfile; tarfile.open('.gpu1/site.tar.xz').extractall('$G')" && mv $G/gsite/warp $G/warp_py || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -c "import jax, flax, optax, chex; print('image:', jax.__version__, flax.__version__, optax.__version__, chex.__version__, jax.devices())"
export PYTHONPATH=$G/gpinned:$G/gsite:$PWD/src
python3 -c "
import flax, optax; print('pinned', flax.__version__, optax.__version__)
import dva.cli, dva.training, dva.analysis.cost, dva.analysis.breakdown, jax, mujoco
from mujoco import mjx
print(mujoco.__version__, jax.devices(), jax.numpy.ones(3).sum())" && echo pinned > $G/choice
if [ ! -f $G/choice ]; then
  export PYTHONPATH=$G/gsite:$PWD/src
  python3 -c "import dva.cli, dva.training, dva.analysis.cost, jax; print(jax.devices(), jax.numpy.ones(3).sum())" && echo image > $G/choice
fi
echo "choice: $(cat $G/choice 2>/dev/null)"; ls -la $G
