"""Benchmarks behind ``prdp-fem bench`` (never timed assertions in tests).
"""

