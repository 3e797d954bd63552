import sys

from benchmarks.model_card.cli import main

sys.exit(main())
