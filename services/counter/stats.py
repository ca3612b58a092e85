"""What the counter reports of a run, in its metrics, final status and info: sizes,
exactness tallies, throughput and query latency. Pure over a `RunState`; the caller
holds the runs' lock."""

from __future__ import annotations

import numpy as np

from services.counter.state import RunState
from shared.net.stats import CounterStats


def run_stats(st: RunState, rejects_total: int) -> CounterStats:
    lat = np.asarray(st.latencies, dtype=np.float64) * 1000.0
    base = st.explorer.stats()
    memory = sum(t.memory_bytes() for t in st.explorer.tables)
    return CounterStats(
        table_size=int(base["table_size"]),
        count1_pct=float(base["count1_pct"]),
        counted_transitions=st.counted,
        duplicates=st.cursor.duplicate_rows,
        gaps=st.cursor.gaps,
        rejects_total=rejects_total,
        run_rejects=st.run_rejects,
        memory_bytes=int(memory),
        transitions_per_sec=round(st.rate, 3),
        query_p50_ms=float(np.percentile(lat, 50)) if lat.size else 0.0,
        query_p99_ms=float(np.percentile(lat, 99)) if lat.size else 0.0,
        queries=st.queries,
        uncounted_rows_queried=st.uncounted_rows_queried,
        wal_records=st.wal.records,
        snapshots=st.snapshots,
        actors=len(st.cursor.positions()),
    )


def update_rate(st: RunState, now: float) -> None:
    """Transitions counted per second since the last update."""
    dt = now - st.rate_t
    if dt > 0:
        st.rate = (st.counted - st.rate_counted) / dt
    st.rate_t, st.rate_counted = now, st.counted
