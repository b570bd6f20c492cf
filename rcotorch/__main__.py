"""``python -m rcotorch``: the command line (see ``rcotorch.cli``)."""

import sys

from .cli import main

sys.exit(main())
