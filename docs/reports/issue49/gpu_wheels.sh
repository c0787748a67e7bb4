#!/usr/bin/env bash
# Issue 49's GPU check, step 1 (here, once per checkout): the wheels the device machine lacks, for its Python 3.12
# (it has torch 2.11 with CUDA, numpy, scipy, pandas, matplotlib, rich, fsspec, tqdm, PyYAML, cloudpickle; not TorchRL,
# TensorDict, gymnasium, MuJoCo, pydantic, omegaconf, greenlet). Into .whl/ (ignored by git), the versions of
# constraints.txt; mujoco-studio (MuJoCo 4's viewer, 13 MB, never imported by a run) is left out so that the tree and
# the wheels stay under the device's 64 MiB. Then run gpu_check.sh there (its header says how).
set -eu
cd "$(git rev-parse --show-toplevel)"
exclude=$(git rev-parse --git-path info/exclude)
mkdir -p "$(dirname "$exclude")" .whl
grep -qx "/.whl/" "$exclude" 2>/dev/null || echo "/.whl/" >> "$exclude"
pin() { grep -i "^$1==" constraints.txt | head -1; }
platforms=""
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_24_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
    manylinux1_x86_64 any; do platforms="$platforms --platform $p"; done
want="$(pin torchrl) $(pin tensordict) $(pin gymnasium) $(pin mujoco) $(pin omegaconf) $(pin pydantic) $(pin greenlet)"
# their own needs, at the versions this checkout's venv (make install) holds, where the device has none
for name in farama-notifications glfw mujoco-core pyopengl pydantic-core annotated-types typing-inspection \
    typing-extensions importlib-metadata orjson pyvers hoptorch; do
  version=$(.venv/bin/python -m pip show "$name" 2>/dev/null | sed -n 's/^Version: //p')
  [ -n "$version" ] || { echo "gpu_wheels.sh: $name is not installed here (make install first)"; exit 1; }
  want="$want $name==$version"
done
for w in $want; do
  .venv/bin/python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    $platforms -d .whl "$w"
done
rm -f .whl/mujoco_studio-*
du -sh .whl
