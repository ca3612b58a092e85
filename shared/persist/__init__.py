"""Files that outlive a process: atomic writes, the write-ahead log,
checkpoints (cuts) and provenance."""
