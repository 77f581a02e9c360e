"""``python -m lfcam``: the same as the ``lfcam`` command."""

import sys

from lfcam.cli import main

sys.exit(main())
