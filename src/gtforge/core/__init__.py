"""Core maths, grouped by concept: cameras and lenses (``camera``, ``lens``), poses (``geometry``), the files' base
models (``schema``); calibration targets (``targets``), the ZED pair (``zed``), the ground truth (``ground_truth``),
measurements on it (``measure``), image alignment (``alignment``). Imports only infra and errors."""
