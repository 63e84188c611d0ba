"""Scene files: the TOML specification, its formulas, and building problems from it.
"""

