"""`python -m cli`: the `splatstream` command, run from a checkout without installing its script."""
import sys

from .main import main

sys.exit(main())
