#!/bin/bash
# Wheels for a GPU machine without registry access: everything jcomps needs beyond a CUDA jax (and the usual
# scientific stack) that GPU images carry, for that machine's Python and platform.
#
#   bash scripts/offline_wheels.sh [DEST=wheels] [PYTHON_VERSION=3.12]     # here, with registry access
#   pip install --no-index --no-deps --target /tmp/site DEST/*.whl            # there (or into its venv)
#   export PYTHONPATH=/tmp/site:$PWD/src
#
# Versions are the project's pins (pyproject.toml). The image must already have jax with CUDA (checked with jax
# 0.11.2 + CUDA 13), numpy, scipy, etils, absl-py, jinja2, pillow, tensorstore, msgpack, pyyaml, rich, treescope,
# typing_extensions, humanize, simplejson, protobuf, psutil, uvloop, aiofiles, prometheus-client and matplotlib;
# `pip download` without --no-deps lists what a barer image lacks.
set -euo pipefail
dest=${1:-wheels}
py=${2:-3.12}
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
         manylinux1_x86_64 manylinux_2_5_x86_64; do
    platforms+=(--platform "$p")
done
python3 -m pip download --no-deps --only-binary=:all: --python-version "$py" --implementation cp "${platforms[@]}" \
    -d "$dest" brax==0.14.2 mujoco==3.3.0 mujoco-mjx==3.3.0 flax==0.12.8 optax==0.2.8 chex==0.1.92 \
    orbax-checkpoint==0.12.8 jaxopt==0.8.5 ml_collections==1.1.0 trimesh==5.2.0 glfw==2.11.0 tensorboardX==2.6.4
du -sh "$dest"
