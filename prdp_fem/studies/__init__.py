"""Studies: the scene runner, forward convergence studies, the stability report and figures.

:func:`run_study` runs every configuration of a scene into an output directory (append-only
records, resumable, one writer per directory) and writes the summary with the savings.
"""

from .runner import StudyError, StudyOutput, run_study, summarize

__all__ = ["StudyError", "StudyOutput", "run_study", "summarize"]
