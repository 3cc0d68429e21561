"""``python -m bridge.cli``: the `hilbo` command."""

import sys

from bridge.cli.main import main

sys.exit(main())
