"""``python -m supervisor.cli`` runs drivectl."""

import sys

from . import main

sys.exit(main())
