import sys

from training.synth.cli import main

sys.exit(main())
