"""`python -m keo_service.cli`: the same as the `keo` console script."""

import sys

from keo_service.cli import console

sys.exit(console())
