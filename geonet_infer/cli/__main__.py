"""``python -m geonet_infer.cli``: the same as the ``geonet-infer`` console script."""

import sys

from geonet_infer.cli import main

sys.exit(main())
