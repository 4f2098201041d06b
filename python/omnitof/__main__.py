"""`python -m omnitof ...`: the `omnitof` command, where the console script is not on PATH
(a virtual environment not activated, an install with --no-scripts)."""

import sys

from omnitof.cli import main

sys.exit(main())
