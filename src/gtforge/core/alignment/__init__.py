"""Image alignment: photometric (shifts between images) and edges (a depth camera against its colour image)."""
