"""``python -m vslam.cli``: the same as the ``vslam`` command."""

import sys

from vslam.cli.app import main

sys.exit(main())
