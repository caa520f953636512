"""The default values of the settings a user sets on the command line, one number in one place: the parameter models
(``BuildParams``, ``ValidateParams``, ``EdgeAlignmentParams``) take their defaults from here, and the command line shows
and passes the same. (The command line cannot read them from the models without importing the maths behind them,
numba included, into ``gtforge --help``.)"""
from __future__ import annotations

# build-dataset (gtforge.records.dataset.BuildParams); validate reprojects with the same mesh rule (ValidateParams)
MAX_SLANT_DEG = 85.0  # mesh: triangles steeper than this are not drawn
EROSION_PX = 15  # fruit centre = the fruit mask eroded by this; edge = the rest
SPLIT_TRAIN = 0.8
SPLIT_VAL = 0.1
SPLIT_SEED = 0

# validate (gtforge.records.validation.ValidateParams): PASS thresholds
XY_THRESHOLD_PX = 0.3
Z_THRESHOLD_PCT = 0.05

# align-depth (gtforge.core.alignment.edge_alignment.EdgeAlignmentParams)
EDGE_SEARCH_PX = 6.0  # the coarse search's first range (+-px)
EDGE_APPLY_Z = 3.0  # apply the correction when it is more than this many sigma from the factory pose

# the stages that fit a few terms to a session's scenes use at most this many scenes, evenly spread over the session
# (calibrate's self-rectification: SelfRectifyParams; calibrate-scale: ScaleParams); refine's extrinsic keeps
# gaining with more (its sigma as 1 / sqrt(scenes)) and holds less a scene (benchmarks/RESULTS.md, round 22)
MAX_SCENES = 24
REFINE_MAX_SCENES = 48
