"""The ``prdp-fem`` command line.
"""

