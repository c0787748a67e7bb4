"""``python -m adarl.experiments.bench``: ``adarl bench`` without the CLI, and its workers' command line."""

import sys

from adarl.experiments.bench._update import main

if __name__ == "__main__":
    sys.exit(main())
