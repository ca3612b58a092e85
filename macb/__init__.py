"""The Python API: runs as pandas DataFrames and a figure's summary from them, the same
numbers and words the report writes (docs/python.md).

    import macb
    frame = macb.load_runs("runs/reproduce/fig8-thesis")
    points = macb.load_page("docs/results/fig8-thesis")  # a page's FIGURE.csv.gz
    s = macb.summary(frame, "fig8")
    with macb.Client("http://127.0.0.1:8000") as api:  # MACB_API_TOKEN, as the CLI
        live = api.experiment_frame(experiment_id)

The top layer: it imports cli/ (the report's functions) and nothing imports it.
"""

from macb.client import ApiError, Client
from macb.runs import CONFIG_PREFIX, RunsError, load_page, load_runs
from macb.summary import FigureSummary, summary

__all__ = [
    "CONFIG_PREFIX",
    "ApiError",
    "Client",
    "FigureSummary",
    "RunsError",
    "load_page",
    "load_runs",
    "summary",
]
