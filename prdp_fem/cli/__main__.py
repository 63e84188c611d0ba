"""``python -m prdp_fem.cli`` runs the command line."""

from .main import run

run()
