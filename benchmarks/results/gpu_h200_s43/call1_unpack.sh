#!/bin/bash
# Call 1 of 3 (carry .gpuA): unpack the packages (cp312 wheels, see ../gpu_h200_s40/README.md) and
# MJX's Humanoid test model into /tmp/g, kept while the machine stays warm; keep Warp's first piece.
G=/tmp/g; mkdir -p $G && cp .gpuA/w0 $G/ || exit 1
python3 -c "import tarfile; tarfile.open('.gpuA/site.tar.xz').extractall('$G')" || exit 1
mkdir -p $G/gsite/mujoco/mjx/test_data && cp -r .gpuA/humanoid $G/gsite/mujoco/mjx/test_data/ || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
PYTHONPATH=$G/gpinned:$G/gsite:$PWD/src python3 -c "import flax, jax, mujoco, dva.cli; print('flax', flax.__version__, 'jax', jax.__version__, 'mujoco', mujoco.__version__, jax.devices())"
du -sh $G
