"""Test-wide settings: one torch/OpenMP thread, in this process and every subprocess the tests start.

On a 2-core machine two threads per process collapse as soon as anything else runs (see docs/performance.md);
one thread is also what the exact-resume guarantee is stated for.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")

import torch  # noqa: E402

torch.set_num_threads(1)
