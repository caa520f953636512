"""Core maths: cameras and lenses, poses, boards and targets, reprojection, rectification, uncertainty, metrics, \
shape fits. Imports only infra and errors."""
