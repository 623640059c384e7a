"""``python -m torchgarment`` runs the command line."""

import sys

from torchgarment.cli import main

sys.exit(main())
