"""What evaluate writes: each scene's ``SceneResult`` and the run's ``EvalResult`` (results.json), the regions they
are scored over and the colour scales of the error maps. Read by the reports and by ``gtforge evaluate --compare``."""
from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from gtforge.core.measure.fruit_size import FruitSizeResult
from gtforge.core.measure.metrics import Metrics
from gtforge.core.schema import VersionedFile

REGIONS = ("all", "nonoccluded", "fruit", "fruit_edge", "fruit_centre", "background")



TABLE_REGIONS = ("all", "fruit", "fruit_edge", "fruit_centre")



DEPTH_REGIONS = ("fruit", "fruit_edge", "fruit_centre")  # regions whose depth error (mm) is scored



DISP_ERROR_MAP_MAX_PX = 2.0  # colour scale of the disparity error maps (the Bad-2.0 threshold; same for every scene)



# the fruit depth-error map's scale: this percentile of the scene's errors, rounded up
DEPTH_ERROR_MAP_PERCENTILE = 95.0



class SceneResult(VersionedFile):

    KIND: ClassVar[str] = "per-scene evaluation result"
    scene: str
    time_ms: float
    metrics: dict[str, Metrics]
    disp_error_map_max_px: float | None = None  # top of the colour scale of heatmaps/<scene>_disp_error.png
    depth_error_map_max_mm: float | None = None  # top of the colour scale of heatmaps/<scene>_depth_error.png



class EvalResult(VersionedFile):

    KIND: ClassVar[str] = "evaluation result (results.json from gtforge evaluate)"
    model: str
    provider: str
    dataset_dir: str
    scenes: list[str]
    missing: dict[str, str] = Field(default_factory=dict)
    # scored scenes whose ground truth verify found suspect: scene -> "quarantined: ..." or "flagged: ..." (its reasons)
    suspect_scenes: dict[str, str] = Field(default_factory=dict)
    model_source: str = ""  # the model file / prediction folder (absolute), or a description of a built-in one
    gtforge_version: str = ""
    created: str = ""  # local time with UTC offset, ISO 8601
    dataset_manifest_sha256: str | None = None  # the manifest file's bytes
    # identifies the labels (Manifest.content_sha256: the manifest without where and when it was built); compare
    # warns when results differ in it (in the file's hash where a result has none: written before it existed)
    dataset_content_sha256: str | None = None
    split: str | None = None
    max_disp_px: float | None = None
    max_gt_sigma_px: float | None = None
    time_ms_median: float | None = None
    params_count: int | None = None
    pooled: dict[str, Metrics]
    per_image_mean: dict[str, Metrics]
    per_scene: list[SceneResult]
    # per-fruit size, volume and grade (gtforge.core.measure.fruit_size); absent in results written before it existed
    fruit_size: "FruitSizeResult | None" = None
