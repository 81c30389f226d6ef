"""``python -m scmr_mesh`` runs the ``scmr`` command line (used to start peers)."""

from scmr_mesh.cli import run

run()
