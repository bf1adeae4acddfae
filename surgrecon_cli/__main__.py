"""`python -m surgrecon_cli ...`: the same as the `surgrecon` command."""

import sys

from .cli.main import main

sys.exit(main())
