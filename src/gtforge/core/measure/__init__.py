"""Measurements on the ground truth: metrics, shape fits, fruit size, gauge objects."""
