"""``python -m scmr_mesh`` runs the ``scmr`` command line (used to start peers)."""

import sys

from scmr_mesh.cli import main

sys.exit(main())
