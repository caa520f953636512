"""The import rule of docs/architecture.md, checked on the source: no import circles, and no module imports a higher
layer (a function-local import counts: it is an edge all the same, it only runs later)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "gtforge"

# Lowest first. A module may import its own layer and the layers below it, never one above.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("infra", ("gtforge.errors", "gtforge._moved", "gtforge.infra")),
    ("core", ("gtforge.core",)),
    ("io", ("gtforge.io",)),
    ("records", ("gtforge.records",)),
    ("reports", ("gtforge.reports",)),
    ("dataset", ("gtforge.dataset",)),
    ("stages", ("gtforge.calibrate", "gtforge.scale_calibration", "gtforge.refine", "gtforge.build_dataset",
                "gtforge.verify", "gtforge.validate", "gtforge.evaluate", "gtforge.predictors", "gtforge.training")),
    ("recipes", ("gtforge.synthetic", "gtforge.demo", "gtforge.run", "gtforge.precompile", "gtforge.cli")),
]


def _graph_module():
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "scripts" / "import_graph.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("import_graph", mod)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def graph():
    g = _graph_module()
    modules, edges = g.graph(SRC)
    edges.pop("gtforge", None)  # the package's __init__: the version and the moved paths' finder
    return g, modules, edges


def test_every_module_is_in_a_layer(graph):
    g, modules, _ = graph
    unplaced = []
    for m in modules:
        if m == "gtforge":
            continue
        try:
            g.layer_of(m, LAYERS)
        except KeyError:
            unplaced.append(m)
    assert unplaced == [], f"add these to LAYERS (tests/test_architecture.py) and docs/architecture.md: {unplaced}"


def test_no_import_circles(graph):
    g, _, edges = graph
    assert g.circles(edges) == []


def test_no_import_goes_up_a_layer(graph):
    g, _, edges = graph
    ups = [f"{m}:{line} imports {tgt} ({LAYERS[g.layer_of(tgt, LAYERS)][0]} is above "
           f"{LAYERS[g.layer_of(m, LAYERS)][0]})" for m, line, tgt in g.upward(edges, LAYERS)]
    assert ups == []


def test_the_checker_sees_a_circle_and_an_upward_import(tmp_path):
    """The rule's checker on a made-up package: it must report what it is there to forbid."""
    g = _graph_module()
    pkg = tmp_path / "gtforge"
    (pkg / "core").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "__init__.py").write_text("")
    (pkg / "core" / "a.py").write_text("def f():\n    from gtforge.calibrate import x\n")
    (pkg / "calibrate.py").write_text("from gtforge.core.a import f\n")
    modules, edges = g.graph(pkg)
    assert g.circles(edges) == [["gtforge.calibrate", "gtforge.core.a"]]
    assert g.upward(edges, LAYERS) == [("gtforge.core.a", 2, "gtforge.calibrate")]


# Names that moved in round 3, at their old paths (docs/architecture.md, "Moved names"): one per kind of move.
OLD_PATHS = [
    ("gtforge.build_dataset", "Manifest"), ("gtforge.build_dataset", "BuildParams"),
    ("gtforge.build_dataset", "fruit_regions"), ("gtforge.build_dataset", "verify_one_scene"),
    ("gtforge.build_dataset", "make_splits"), ("gtforge.calibrate", "CalibrationFile"),
    ("gtforge.calibrate", "open_calibrated_session"), ("gtforge.calibrate", "PoseReport"),
    ("gtforge.calibrate", "solve_pnp"), ("gtforge.evaluate", "EvalReport"), ("gtforge.evaluate", "TABLE_REGIONS"),
    ("gtforge.verify", "VerifyParams"), ("gtforge.verify", "local_normalize"), ("gtforge.verify", "render_texture"),
    ("gtforge.validate", "REFERENCE_XY_PX"), ("gtforge.validate", "ValidationReport"),
    ("gtforge.scale_calibration", "corrected_right_image"), ("gtforge.scale_calibration", "ScaleCalibration"),
    ("gtforge.synthetic", "BoardSpec"), ("gtforge.synthetic", "GridCounts"), ("gtforge.io.formats", "to_gray"),
    ("gtforge.camera", "Rig"), ("gtforge.scheduling", "run_tasks"), ("gtforge.io.atomic", "atomic_write_text"),
    ("gtforge.rectification", "settle_zed_conf_reading"), ("gtforge.rectification", "summary_lines"),
    ("gtforge.selfcal", "self_rectify"), ("gtforge.targets", "detect_charuco"), ("gtforge.targets", "matched_points"),
    ("gtforge.gauges", "validate_gauges"), ("gtforge.reproject", "reproject_to_zed"),
]


@pytest.mark.parametrize("module, name", OLD_PATHS)
def test_a_moved_name_still_imports_from_its_old_path(module, name):
    import importlib
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        old = importlib.import_module(module)
        value = getattr(old, name)
    assert value is not None
    # and it is the very object of its new home (not a copy)
    homes = [m for m in sys.modules.values() if getattr(m, "__name__", "").startswith("gtforge.")
             and not getattr(m, "__gtforge_homes__", None) and m.__dict__.get(name) is value]
    assert homes, f"{module}.{name} is not any gtforge module's own object"


def test_a_moved_module_warns_with_its_new_path():
    import importlib
    import warnings

    sys.modules.pop("gtforge.lens", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = importlib.import_module("gtforge.lens")
    assert any("gtforge.core.lens" in str(w.message) for w in caught)
    from gtforge.core import lens

    assert old.undistort is lens.undistort
