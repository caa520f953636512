"""The ground truth: depth moved into a camera (reproject, and its float64 reference), texture rendered through it
(render), region labels (regions), per-pixel sigma (uncertainty)."""
