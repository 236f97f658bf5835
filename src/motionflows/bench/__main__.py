"""``python -m motionflows.bench``: the same as ``motionflows bench``."""

import sys

from motionflows.cli_bench import main

sys.exit(main(sys.argv[1:]))
