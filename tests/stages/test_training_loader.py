"""gtforge.training.StereoDataset on the layouts a built dataset offers (a hand-made two-scene dataset: no build)."""
from __future__ import annotations

import numpy as np
import pytest

from gtforge.errors import InputError
from gtforge.io.formats import write_image, write_kitti_disparity, write_pfm, write_tiff_float
from gtforge.training import StereoDataset


def _dataset(root):
    rng = np.random.default_rng(0)
    for sid in ("000", "001"):
        s = root / "scenes" / sid
        s.mkdir(parents=True)
        disp = np.full((6, 8), 20.25 + int(sid), np.float32)
        disp[0, 0] = np.nan
        write_image(s / "im0.png", rng.integers(0, 255, (6, 8, 3), dtype=np.uint8))
        write_image(s / "im1.png", rng.integers(0, 255, (6, 8, 3), dtype=np.uint8))
        write_pfm(s / "disp0GT.pfm", disp)
        write_tiff_float(s / "weight.tiff", np.where(np.isfinite(disp), 1.4, 0.0).astype(np.float32))
        k = root / "kitti" / "training"
        for d in ("image_2", "image_3", "disp_occ_0"):
            (k / d).mkdir(parents=True, exist_ok=True)
        (k / "image_2" / f"{sid}_10.png").write_bytes((s / "im0.png").read_bytes())
        (k / "image_3" / f"{sid}_10.png").write_bytes((s / "im1.png").read_bytes())
        write_kitti_disparity(k / "disp_occ_0" / f"{sid}_10.png", disp)
    (root / "filenames").mkdir()
    (root / "filenames" / "train.txt").write_text("scenes/001/im0.png scenes/001/im1.png scenes/001/disp0GT.pfm\n")
    (root / "filenames" / "kitti_train.txt").write_text(
        "training/image_2/001_10.png training/image_3/001_10.png training/disp_occ_0/001_10.png\n")
    (root / "filenames" / "test.txt").write_text("")
    return root


def test_the_kitti_lists_load_the_same_scene_as_the_middlebury_ones(tmp_path):
    """StereoDataset(OUT, 'kitti_train') joined the list's paths (relative to OUT/kitti) to OUT and read the KITTI PNG
    as a PFM: 'OUT/training/disp_occ_0/001_10.png: expected a readable PFM file, got No such file or directory'."""
    root = _dataset(tmp_path / "ds")
    mid, kit = StereoDataset(root, "train"), StereoDataset(root, "kitti_train")
    assert len(mid) == len(kit) == 1
    a, b = mid[0], kit[0]
    assert a["scene"] == b["scene"] == "001"
    np.testing.assert_array_equal(a["left"], b["left"])
    np.testing.assert_array_equal(a["right"], b["right"])
    np.testing.assert_array_equal(a["valid"], b["valid"])
    assert not b["valid"][0, 0] and b["valid"].sum() == 47
    np.testing.assert_allclose(b["disparity"][b["valid"]], 21.25)  # a multiple of 1/256: exact in the PNG
    np.testing.assert_array_equal(b["weight"], a["weight"])
    assert b["sigma"] is None  # no disp0GT_sigma.pfm in this dataset


def test_an_empty_split_and_a_folder_that_is_no_dataset(tmp_path):
    root = _dataset(tmp_path / "ds")
    assert len(StereoDataset(root, "test")) == 0
    assert [it["scene"] for it in StereoDataset(root, None)] == ["000", "001"]
    with pytest.raises(InputError, match=r"nowhere/scenes: expected a built dataset's scenes folder, got no such "
                                         r"file \(hint: "):
        StereoDataset(tmp_path / "nowhere", None)
    with pytest.raises(InputError, match=r"filenames/kitti_nope.txt: expected a 'kitti_nope' list, got no such file"):
        StereoDataset(root, "kitti_nope")
    (root / "scenes" / "001" / "weight.tiff").unlink()
    with pytest.raises(InputError, match=r"001/weight.tiff: expected the scene's SGRA weight map, got no such file"):
        StereoDataset(root, "kitti_train")[0]


def test_a_damaged_or_missing_dataset_file_is_one_line_naming_it_with_the_builds_hint(tmp_path):
    """A weight.tiff cut to nothing raised tifffile's 'TiffFileError: not a TIFF file: header=b''' (no file named, no
    InputError); a KITTI image missing said 'check the capture folder / session.yaml' (a capture's hint, for a file
    build-dataset writes). The weight read as before: float32, the values written."""
    root = _dataset(tmp_path / "ds")
    w = StereoDataset(root, "train")[0]["weight"]
    assert w.dtype == np.float32 and w[0, 0] == 0.0 and np.all(w.ravel()[1:] == np.float32(1.4))
    (root / "scenes" / "001" / "weight.tiff").write_bytes(b"")
    with pytest.raises(InputError) as e:
        StereoDataset(root, "train")[0]
    assert e.value.file == str(root / "scenes" / "001" / "weight.tiff") and e.value.expected == "a readable image"
    write_tiff_float(root / "scenes" / "001" / "weight.tiff", w)
    (root / "kitti" / "training" / "image_3" / "001_10.png").unlink()
    with pytest.raises(InputError) as e:
        StereoDataset(root, "kitti_train")[0]
    assert e.value.file == str(root / "kitti" / "training" / "image_3" / "001_10.png")
    assert "build-dataset" in e.value.hint and "capture folder" not in e.value.hint


def test_a_list_line_without_three_paths_is_one_line_naming_the_list_and_line(tmp_path):
    """A split list of one's own whose line lacks the disparity's path: refused when the loader is made, naming the
    list and the line (a bare 'ValueError: not enough values to unpack' came when that sample was read)."""
    root = _dataset(tmp_path / "ds")
    (root / "filenames" / "mine.txt").write_text("scenes/000/im0.png scenes/000/im1.png scenes/000/disp0GT.pfm\n\n"
                                                 "scenes/001/im0.png scenes/001/im1.png\n")
    with pytest.raises(InputError) as e:
        StereoDataset(root, "mine")
    assert e.value.file == str(root / "filenames" / "mine.txt") and e.value.field == "line 3"
    assert e.value.actual == "2 ('scenes/001/im0.png scenes/001/im1.png')"
    (root / "filenames" / "mine.txt").write_text("scenes/001/im0.png scenes/001/im1.png scenes/001/disp0GT.pfm\n")
    assert StereoDataset(root, "mine")[0]["scene"] == "001"
