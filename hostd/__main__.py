"""`python -m hostd` is the `hostd` command."""

import sys

from hostd.cli.main import main

sys.exit(main())
