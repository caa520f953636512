"""I/O boundary: vendor readers and dataset writers. Invalid-value encodings live here only."""
