"""The Python API: runs as pandas DataFrames and a figure's summary from them, the same
numbers and words the report writes (docs/python.md).

    import macb
    frame = macb.load_runs("runs/reproduce/fig8-thesis")
    s = macb.summary(frame, "fig8")

The top layer: it imports cli/ (the report's functions) and nothing imports it.
"""

from macb.runs import CONFIG_PREFIX, RunsError, load_runs
from macb.summary import FigureSummary, summary

__all__ = ["CONFIG_PREFIX", "FigureSummary", "RunsError", "load_runs", "summary"]
