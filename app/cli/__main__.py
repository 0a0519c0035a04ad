"""`python -m app.cli ARGS` is `omniformation ARGS`."""

import sys

from app.cli import main

sys.exit(main())
