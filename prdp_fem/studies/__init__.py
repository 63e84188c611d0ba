"""Studies: the scene runner, forward convergence studies, the stability report and figures.
"""

