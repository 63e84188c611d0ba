"""``python -m prdp_fem`` runs the command line."""

from .cli.main import run

run()
