"""``python -m facecast.cli``: the ``facecast`` command, as the console script runs it."""

import sys

from facecast.cli.main import main

sys.exit(main())
