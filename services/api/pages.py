"""The API's pages (the dashboard, the figure view) as served: each HTML file with the
charts' script (charts.js) inlined, so both pages draw with the one chart function and a
page needs no second request that a bearer token would have to cover. `macb view`
(cli/view.py) serves figure.html the same way.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).parent
SCRIPT_TAG = '<script src="charts.js"></script>'


def page(name: str) -> str:
    """`name` (an HTML file beside this module) with charts.js inlined."""
    html = (HERE / name).read_text()
    script = (HERE / "charts.js").read_text()
    return html.replace(SCRIPT_TAG, f"<script>\n{script}</script>", 1)
