"""``python -m vtolpose``: the same command line as the ``vtolpose`` script."""

import sys

from vtolpose.service.cli import main

sys.exit(main())
