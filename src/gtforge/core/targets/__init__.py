"""Calibration targets: board models and their rendering (board, models), detection in images (detection), where the
points fell (coverage), the extrinsic from board poses (extrinsic)."""
