"""``python -m cellbridge`` runs the same command as the ``cellbridge`` script."""

import sys

from cellbridge.cli import main

sys.exit(main())
