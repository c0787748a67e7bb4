"""Side-by-side SAC speed benchmark; the same as ``adarl bench`` (see docs/performance.md).

PYTHONPATH=. python benchmarks/sac_speed.py --envs Hopper-v5 --widths 64 256 --output benchmarks/results/hopper.json
"""

import sys

from adarl.experiments.bench import main

if __name__ == "__main__":
    sys.exit(main())
