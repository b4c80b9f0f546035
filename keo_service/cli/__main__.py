"""`python -m keo_service.cli`: the same as the `keo` console script."""

import signal
import sys

# a stop asked while the CLI still imports ends it quietly too (exit 0), as in `console`
signal.signal(signal.SIGTERM, signal.default_int_handler)
try:
    from keo_service.cli import console
except KeyboardInterrupt:
    sys.exit(0)

sys.exit(console())
