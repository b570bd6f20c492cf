"""``python -m rcotorch``: the command line (see ``rcotorch.run.cli``)."""

import sys

from .run.cli import main

sys.exit(main())
