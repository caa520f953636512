import os

import numpy as np
import pytest

from tests.conftest import shared_data

from gtforge.errors import InputError
from gtforge.infra.atomic import atomic_path, atomic_write_text
from gtforge.io.formats import (
    read_image,
    read_kitti_disparity,
    read_pfm,
    read_ply_points,
    write_image,
    write_kitti_disparity,
    write_pfm,
    write_ply,
    write_tiff_float,
)


def test_pfm_layout_and_invalid(tmp_path):
    d = np.array([[1.5, np.nan, 3.0], [4.0, -np.inf, np.inf]], np.float32)
    p = write_pfm(tmp_path / "d.pfm", d)
    raw = p.read_bytes()
    assert raw.startswith(b"Pf\n3 2\n-1.0\n")  # negative scale = little-endian
    body = np.frombuffer(raw[len(b"Pf\n3 2\n-1.0\n"):], "<f4").reshape(2, 3)
    np.testing.assert_array_equal(body[0], [4.0, np.inf, np.inf])  # rows bottom-to-top; any invalid value: +inf
    assert body[1, 1] == np.inf  # NaN written as +inf
    back = read_pfm(p)
    np.testing.assert_array_equal(np.isnan(back), [[False, True, False], [False, True, True]])
    np.testing.assert_array_equal(back[0, [0, 2]], [1.5, 3.0])


def test_pfm_truncated(tmp_path):
    p = write_pfm(tmp_path / "d.pfm", np.ones((4, 5), np.float32))
    p.write_bytes(p.read_bytes()[:-7])
    with pytest.raises(InputError, match="truncated"):
        read_pfm(p)


@pytest.mark.parametrize("scale", [b".", b"-e", b"--1", b"1e", b"0.0", b"-0", b"1e999"])
def test_pfm_scale_that_is_no_number(tmp_path, scale):
    """A scale the header's pattern lets through but that is no number: one line naming the header, not a ValueError
    (a prediction 000.pfm with the scale '.' stopped gtforge evaluate with a traceback); a zero or infinite scale,
    whose sign gives no byte order, likewise (0.0 was read as big-endian: little-endian data became nonsense)."""
    p = tmp_path / "d.pfm"
    p.write_bytes(b"Pf\n3 2\n" + scale + b"\n" + np.ones((2, 3), "<f4").tobytes())
    with pytest.raises(InputError) as e:
        read_pfm(p)
    assert e.value.field == "header" and repr(scale.decode()) in str(e.value)
    p.write_bytes(b"Pf\n3 2\n-1.0\n" + np.full((2, 3), 2.5, "<f4").tobytes())  # the same bytes with a number
    np.testing.assert_array_equal(read_pfm(p), np.full((2, 3), 2.5, np.float32))


def test_kitti_png_encoding(tmp_path):
    d = np.array([[0.0, 1.0 / 1024, 12.3456], [np.nan, -1.0, 200.0]], np.float32)
    p = write_kitti_disparity(tmp_path / "d.png", d)
    q = read_image(p, expect="uint16")
    np.testing.assert_array_equal(q, [[1, 1, round(12.3456 * 256)], [0, 0, 51200]])  # true 0 -> 1, invalid -> 0
    back = read_kitti_disparity(p)
    assert np.isnan(back[1, 0]) and np.isnan(back[1, 1])
    assert abs(back[0, 2] - 12.3456) <= 0.5 / 256


def test_tiff_and_ply(tmp_path):
    a = np.array([[1.0, np.nan], [3.5, 4.25]], np.float32)
    write_tiff_float(tmp_path / "a.tiff", a)
    import tifffile

    b = tifffile.imread(tmp_path / "a.tiff")
    assert b.dtype == np.float32 and np.isnan(b[0, 1]) and b[1, 1] == 4.25
    pts = np.array([[0, 1, 2], [3, 4, 5.5]])
    write_ply(tmp_path / "c.ply", pts, np.array([[1, 0, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(read_ply_points(tmp_path / "c.ply"), pts)


def test_image_round_trip_and_truncated(tmp_path):
    img = (np.arange(30 * 40 * 3) % 251).astype(np.uint8).reshape(30, 40, 3)
    p = write_image(tmp_path / "i.png", img)
    np.testing.assert_array_equal(read_image(p), img)  # RGB in memory
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(InputError) as e:
        read_image(p)
    assert "i.png" in str(e.value) and "\n" not in str(e.value)


def test_atomic_write_keeps_original_on_failure(tmp_path):
    target = tmp_path / "f.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["f.txt"]


def test_private_folder_writes_final_names_directly(tmp_path, monkeypatch):
    """In a private folder (a scene's hidden temporary folder) the writers skip the temporary file and rename; beside it
    and in its subfolders they stay atomic; the files get the same mode either way."""
    import tempfile

    from gtforge.infra.atomic import file_mode, private_folder
    from gtforge.io.formats import write_label_png

    private = tmp_path / ".tmp-scene"
    private.mkdir()
    made = []
    real_mkstemp = tempfile.mkstemp
    monkeypatch.setattr(tempfile, "mkstemp", lambda *a, **k: made.append(k["dir"]) or real_mkstemp(*a, **k))
    a = np.arange(12, dtype=np.uint8).reshape(3, 4)
    with private_folder(private):
        write_label_png(private / "m.png", a)
        write_pfm(private / "d.pfm", a.astype(np.float32))
        atomic_write_text(private / "calib.txt", "x")
        write_label_png(private / "sub" / "m.png", a)  # a subfolder: atomic
        write_label_png(tmp_path / "beside.png", a)  # another folder: atomic
    assert made == [private / "sub", tmp_path]
    write_label_png(private / "after.png", a)  # after the context: atomic again
    assert made[-1] == private
    np.testing.assert_array_equal(read_image(private / "m.png"), a)
    assert sorted(os.listdir(private)) == ["after.png", "calib.txt", "d.pfm", "m.png", "sub"]
    assert all((private / n).stat().st_mode & 0o777 == file_mode() for n in ("m.png", "d.pfm", "after.png"))


def test_label_png_and_kitti_quantisation(tmp_path):
    import cv2
    from PIL import Image

    from gtforge.io import formats
    from gtforge.io.formats import write_label_png

    lab = (np.arange(37 * 53) % 4).astype(np.uint8).reshape(37, 53)
    q = (np.arange(37 * 53) * 41 % 65536).astype(np.uint16).reshape(37, 53)
    one = np.array([[65535]], np.uint16)
    # gtforge writes the PNG container itself (zlib-ng deflates): three independent decoders read it back exactly
    for name, a in (("r.png", lab), ("q.png", q), ("one.png", one), ("col.png", lab[:, :1].copy())):
        p = write_label_png(tmp_path / name, a)
        np.testing.assert_array_equal(read_image(p, expect="uint16" if a.dtype == np.uint16 else None), a)
        np.testing.assert_array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), a)
        with Image.open(p) as im:
            im.verify()  # chunk CRCs and structure
        with Image.open(p) as im:
            np.testing.assert_array_equal(np.asarray(im).astype(a.dtype), a)
    for bad in (np.zeros((4, 5, 3), np.uint8), np.zeros((4, 5), np.float32), np.zeros((0, 5), np.uint8)):
        with pytest.raises(ValueError):
            write_label_png(tmp_path / "x.png", bad)
    # round(d * 256) half to even, 1 for a valid d that rounds to 0, 0 for NaN / inf / < 0 and for a d beyond 16 bits
    # (a clip would make 300 px a valid 255.996 px label)
    d = np.array([[0.001, 1.5 / 256, 2.5 / 256, 10.0, 300.0], [np.nan, np.inf, -0.5, 0.0, 100.123]], np.float32)
    raw = cv2.imread(str(write_kitti_disparity(tmp_path / "k.png", d)), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(raw, [[1, 2, 2, 2560, 0], [0, 0, 0, 1, round(100.123 * 256)]])
    edge = np.array([[np.nextafter(np.float32(formats.KITTI_MAX_DISPARITY_PX), np.float32(0)),
                      formats.KITTI_MAX_DISPARITY_PX, 65535 / 256]], np.float32)
    np.testing.assert_array_equal(cv2.imread(str(write_kitti_disparity(tmp_path / "e.png", edge)),
                                             cv2.IMREAD_UNCHANGED), [[65535, 0, 65535]])  # (65535.5 rounds to even)
    back = read_kitti_disparity(tmp_path / "k.png")
    assert np.isnan(back[1, :3]).all() and back[0, 3] == 10.0
    # disp_noc: the same values inside the mask, 0 outside it
    noc = np.array([[True, False, True, True, False], [True, True, False, True, True]])
    raw_noc = cv2.imread(str(write_kitti_disparity(tmp_path / "n.png", d, noc)), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(raw_noc, np.where(noc, raw, 0))
    with pytest.raises(ValueError):
        write_kitti_disparity(tmp_path / "x.png", d, noc[:, :4])


def test_kitti_pair_is_two_single_writes_byte_for_byte(tmp_path):
    """disp_occ + disp_noc written together (row blocks without an occluded valid pixel deflated once, for both) are
    the files two write_kitti_disparity calls write, for heights around the block size; three decoders agree."""
    import cv2
    from PIL import Image

    from gtforge.io import formats

    rng = np.random.default_rng(3)
    n = formats.LABEL_PNG_BLOCK_ROWS
    for h in (1, n - 1, n, n + 1, 3 * n + 5):
        d = rng.uniform(0, 200, (h, 29)).astype(np.float32)
        d[rng.random(d.shape) < 0.3] = np.nan
        d[0, :14] = [0.0, -0.0, 1e-40, 0.5 / 256, 1.5 / 256, 2.5 / 256, 255.998, 255.99805, 256.0, 1e10, 3e38, np.inf,
                     -np.inf, -1.0]  # rounding halves, the clips at 1 and 65535, invalid values
        if h > 2 * n:  # blocks without a valid pixel (taken deflated once a size): a whole one and the last, shorter
            d[2 * n:] = np.nan
        noc = np.ones(d.shape, bool)
        noc[h // 2, 3:9] = False  # occluded pixels in one block only (some of them NaN: not a difference)
        noc[~np.isfinite(d[:, 0]), 0] = False  # outside the mask where invalid anyway: no difference either
        po, pn = formats.write_kitti_disparity_pair(tmp_path / "o.png", tmp_path / "n.png", d, noc)
        so, sn = formats.write_kitti_disparity(tmp_path / "so.png", d), \
            formats.write_kitti_disparity(tmp_path / "sn.png", d, noc)
        assert po.read_bytes() == so.read_bytes() and pn.read_bytes() == sn.read_bytes()
        q = formats._kitti_quantize(d, np.ones(d.shape, bool))
        d64 = d.astype(np.float64)  # the definition, in float64 (the kernels quantise in float32)
        with np.errstate(invalid="ignore"):
            valid = (d64 >= 0) & (np.rint(d64 * 256.0) <= 65535)
            np.testing.assert_array_equal(q, np.where(valid, np.maximum(np.rint(d64 * 256.0), 1), 0))
        for path, want in ((po, q), (pn, np.where(noc, q, 0))):
            np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), want)
            np.testing.assert_array_equal(read_image(path, expect="uint16"), want)
            with Image.open(path) as im:
                im.verify()
        _, same, zero, _ = formats._kitti_png_rows(d, noc)
        np.testing.assert_array_equal(zero, (q == 0).all(axis=1))
        differs = np.isfinite(d[h // 2, 3:9]).any()
        np.testing.assert_array_equal(~same, np.arange(h) == h // 2 if differs else np.zeros(h, bool))
    with pytest.raises(ValueError):
        formats.write_kitti_disparity_pair(tmp_path / "o.png", tmp_path / "n.png", d, noc[:, :4])


def test_label_png_blocks_are_the_same_bytes_where_rows_are_the_same():
    """A block of rows deflated alone is the same bytes wherever those rows occur (what lets ``disp_occ`` and
    ``disp_noc`` share blocks), another where one row differs, and the streams decode to their images."""
    import zlib

    from gtforge.io import formats

    n = formats.LABEL_PNG_BLOCK_ROWS
    a = (np.arange((2 * n + 3) * 40) % 251).astype(np.uint8).reshape(2 * n + 3, 40)
    b = a.copy()
    b[n + 2, 7] ^= 1  # one byte of the second block
    rows_a = np.concatenate([np.zeros((a.shape[0], 1), np.uint8), a], axis=1)
    rows_b = np.concatenate([np.zeros((b.shape[0], 1), np.uint8), b], axis=1)
    blocks_a, blocks_b = formats._deflate_blocks(rows_a), formats._deflate_blocks(rows_b)
    assert [x == y for x, y in zip(blocks_a, blocks_b)] == [True, False, True]
    for rows, blocks in ((rows_a, blocks_a), (rows_b, blocks_b)):
        png = formats._png_bytes(40, rows.shape[0], 8, blocks, zlib.adler32(rows))
        assert zlib.decompress(png[png.index(b"IDAT") + 4:-16]) == rows.tobytes()  # (adler-32 checked by zlib)
        np.testing.assert_array_equal(formats.decode_png(png), rows[:, 1:])


def test_float_tiff_compression_round_trip(tmp_path):
    import cv2
    import tifffile

    a = np.linspace(300, 900, 150 * 20, dtype=np.float32).reshape(150, 20)  # 3 strips of 64 rows when compressed
    a[3, 4] = a[149, 19] = np.nan
    for comp, tag in (("none", 1), ("zlib", 8)):
        p = write_tiff_float(tmp_path / f"{comp}.tiff", a, compression=comp)
        with tifffile.TiffFile(p) as t:
            assert t.pages[0].compression == tag
        np.testing.assert_array_equal(tifffile.imread(p), a)
        np.testing.assert_array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), a)


def _png_with_filters(a: np.ndarray, kinds: list[int]) -> bytes:
    """PNG bytes of 8-bit ``a`` ((H, W) or (H, W, C)) with row v filtered by ``kinds[v % len(kinds)]`` (the PNG
    specification's five filters, written out here so the decoder sees each; Pillow reads the result back)."""
    import struct

    from zlib_ng import zlib_ng

    h, w = a.shape[:2]
    ch = 1 if a.ndim == 2 else a.shape[2]
    x = a.reshape(h, w * ch).astype(np.int32)
    rows = []
    for v in range(h):
        cur, up = x[v], (x[v - 1] if v else np.zeros_like(x[v]))
        left = np.concatenate([np.zeros(ch, np.int32), cur[:-ch]])
        upleft = np.concatenate([np.zeros(ch, np.int32), up[:-ch]])
        k = kinds[v % len(kinds)]
        if k == 4:
            p = left + up - upleft
            pa, pb, pc = abs(p - left), abs(p - up), abs(p - upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
        else:
            pred = [np.zeros_like(cur), left, up, (left + up) // 2][k]
        rows.append(bytes([k]) + ((cur - pred) % 256).astype(np.uint8).tobytes())

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib_ng.crc32(kind + data))

    colour = {1: 0, 2: 4, 3: 2, 4: 6}[ch]
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
            + chunk(b"IDAT", zlib_ng.compress(b"".join(rows), 6)) + chunk(b"IEND", b""))


@pytest.fixture(params=["isal", "zlib_ng"])
def png_inflate_lib(request, monkeypatch):
    """decode_png with each inflate backend: ISA-L, and zlib-ng (the fallback where isal has no wheel)."""
    import gtforge.io.formats as formats

    if request.param == "isal":
        lib = pytest.importorskip("isal.isal_zlib")
    else:
        from zlib_ng import zlib_ng as lib
    monkeypatch.setattr(formats, "_png_inflate_lib", lib)
    return request.param


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_decode_png_matches_pillow_for_every_filter(channels, png_inflate_lib):
    """gtforge's PNG decoder (ISA-L or zlib-ng inflate + compiled unfilter) against Pillow through imageio, on every
    filter type, each also on the first row (where the row above is zeros) and on noise (where every byte wraps)."""
    import imageio.v3 as iio

    from gtforge.io.formats import decode_png

    rng = np.random.default_rng(channels)
    shape = (23, 31) if channels == 1 else (23, 31, channels)
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    smooth = (np.add.outer(np.arange(23) * 9, np.arange(31) * 5) % 256).astype(np.uint8)
    smooth = smooth if channels == 1 else np.repeat(smooth[..., None], channels, axis=2)
    for img in (noise, smooth):
        for kinds in ([0], [1], [2], [3], [4], [4, 3, 2, 1, 0]):
            data = _png_with_filters(img, kinds)
            got = decode_png(data)
            np.testing.assert_array_equal(got, img)
            np.testing.assert_array_equal(got, iio.imread(data))
            for rows in (0, 1, 6, 22, 23, 40):  # the first rows only (all of them from 23 on)
                part = decode_png(data, rows)
                assert part.shape == img[:rows].shape
                np.testing.assert_array_equal(part, img[:rows])


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_decode_png_sub_rows_in_pairs_and_alone(channels):
    """Sub-filtered rows are undone two at a time, 8 bytes at a time (``_unfilter_sub_rows``), the row's last bytes one
    by one: rows of fewer than 8 bytes, of a multiple of 8 bytes and between, Sub rows in pairs, alone and last,
    against the image itself and Pillow."""
    import imageio.v3 as iio

    from gtforge.io.formats import decode_png

    rng = np.random.default_rng(10 + channels)
    for w in (1, 2, 3, 8, 16, 21, 43):
        shape = (9, w) if channels == 1 else (9, w, channels)
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        for kinds in ([1], [1, 1, 2], [2, 1, 1, 1], [1, 0, 1, 4, 1, 1, 3]):
            data = _png_with_filters(img, kinds)
            got = decode_png(data)
            np.testing.assert_array_equal(got, img)
            np.testing.assert_array_equal(got, iio.imread(data))
            for rows in (1, 2, 5):
                np.testing.assert_array_equal(decode_png(data, rows), img[:rows])


def test_decode_png_16bit_grey_and_the_variants_left_to_imageio(tmp_path, png_inflate_lib):
    import cv2
    import imageio.v3 as iio

    from gtforge.io.formats import decode_png

    q = (np.arange(20 * 30, dtype=np.uint32).reshape(20, 30) * 97 % 65536).astype(np.uint16)
    data = cv2.imencode(".png", q)[1].tobytes()  # OpenCV: adaptive filters, big-endian samples
    got = decode_png(data)
    assert got.dtype == np.uint16 and got.dtype.isnative
    np.testing.assert_array_equal(got, q)
    rgb16 = np.repeat(q[..., None], 3, axis=2)
    assert decode_png(cv2.imencode(".png", rgb16)[1].tobytes()) is None  # 16-bit colour: imageio's (8-bit) result
    from PIL import Image

    Image.fromarray(np.arange(600, dtype=np.uint8).reshape(20, 30) % 7, mode="L").convert("P").save(tmp_path / "p.png")
    assert decode_png((tmp_path / "p.png").read_bytes()) is None  # palette
    np.testing.assert_array_equal(read_image(tmp_path / "p.png"), iio.imread(tmp_path / "p.png"))


def test_decode_png_rejects_corrupt_and_truncated_data(tmp_path, png_inflate_lib):
    from gtforge.io.formats import decode_png

    img = (np.arange(40 * 50 * 3) % 253).astype(np.uint8).reshape(40, 50, 3)
    data = _png_with_filters(img, [1, 4])
    idat = data.index(b"IDAT")
    flipped = bytearray(data)
    flipped[idat + 40] ^= 0x10
    with pytest.raises(ValueError, match="CRC mismatch in the IDAT chunk"):
        decode_png(bytes(flipped))
    with pytest.raises(ValueError, match="truncated"):
        decode_png(data[: len(data) - 30])
    import struct

    from zlib_ng import zlib_ng

    n = struct.unpack(">I", data[idat - 4:idat])[0]  # rewrite row 3's filter type to 5 (unknown), CRC made valid
    raw = bytearray(zlib_ng.decompress(data[idat + 4:idat + 4 + n]))
    raw[3 * (1 + 50 * 3)] = 5
    body = zlib_ng.compress(bytes(raw))
    forged = (data[:idat - 4] + struct.pack(">I", len(body)) + b"IDAT" + body
              + struct.pack(">I", zlib_ng.crc32(b"IDAT" + body)) + data[idat + 8 + n:])
    with pytest.raises(ValueError, match="unknown filter type on row 3"):
        decode_png(forged)
    half = data[idat + 4:idat + 4 + n // 2]  # the deflate stream cut in half, in a well-formed chunk
    cut_stream = (data[:idat - 4] + struct.pack(">I", len(half)) + b"IDAT" + half
                  + struct.pack(">I", zlib_ng.crc32(b"IDAT" + half)) + data[idat + 8 + n:])
    with pytest.raises(ValueError, match=r"does not inflate to 6040 bytes \(truncated"):
        decode_png(cut_stream)
    # the first rows of the cut stream are there; rows past its end are not
    np.testing.assert_array_equal(decode_png(cut_stream, 10), img[:10])
    with pytest.raises(ValueError, match="the image data ends before row 39 \\(truncated\\)"):
        decode_png(cut_stream, 39)
    with pytest.raises(ValueError, match="unknown filter type on row 3"):
        decode_png(forged, 4)
    p = tmp_path / "cut.png"
    p.write_bytes(data[: len(data) - 30])
    with pytest.raises(InputError, match=r"cut\.png.*truncated") as e:
        read_image(p)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("shape", [(1, 1), (23, 31), (1, 7, 3), (23, 31, 3), (40, 1, 3)])
def test_encode_png_decodes_the_same_in_every_reader(shape, tmp_path):
    """``encode_png`` (filter Up on every row, ISA-L deflate): OpenCV, Pillow (imageio) and gtforge's own decoder read
    back the same pixels, on noise (every byte wraps in the filter) and on a smooth image; ``write_image`` writes it."""
    pytest.importorskip("isal")
    import cv2
    import imageio.v3 as iio

    from gtforge.io.formats import decode_png, encode_png

    rng = np.random.default_rng(sum(shape))
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    ramp = np.add.outer(np.arange(shape[0]) * 9, np.arange(shape[1]) * 5) % 256
    smooth = (ramp if len(shape) == 2 else np.repeat(ramp[..., None], 3, axis=2) + np.arange(3) * 40) % 256
    for img in (noise, smooth.astype(np.uint8), np.asfortranarray(noise)):
        data = encode_png(img)
        assert data is not None and data[:8] == b"\x89PNG\r\n\x1a\n"
        np.testing.assert_array_equal(iio.imread(data), img)
        np.testing.assert_array_equal(decode_png(data), img)
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(bgr if img.ndim == 2 else bgr[..., ::-1], img)
        p = write_image(tmp_path / "x.png", img)
        assert p.read_bytes() == data
    assert encode_png(noise.astype(np.uint16)) is None and encode_png(np.zeros((0, 4), np.uint8)) is None
    assert encode_png(np.zeros((2, 2, 4), np.uint8)) is None  # RGBA: OpenCV's, as before


def test_encode_png_of_real_images_is_no_larger_than_opencvs():
    """On real camera images (the ZED Mini raw pair, Middlebury 2014 Motorcycle) the faster encoder's files are within
    5 % of OpenCV's default PNG (the ZED image is smaller: 0.82 against 0.92 MB), and hold the same pixels."""
    pytest.importorskip("isal")
    import cv2

    from gtforge.io.formats import encode_png

    for path in (shared_data("zed-mini-raw-pair") / "right_raw.png",
                 shared_data("middlebury2014-motorcycle-Q") / "im1.png"):
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        rgb = bgr[..., ::-1]
        data = encode_png(rgb)
        assert len(data) <= 1.05 * len(cv2.imencode(".png", bgr)[1]), path
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), bgr)


def test_a_16_bit_colour_png_where_one_channel_is_expected_is_named_as_it_is(tmp_path):
    """A KITTI-style disparity saved as a 16-bit RGB PNG: imageio (Pillow) reduces it to 8 bits, so the refusal said
    'got uint8 with shape (H, W, 3)', naming what the reader made of the file, not the file (a run-through)."""
    import cv2

    p = tmp_path / "rgb16.png"
    cv2.imwrite(str(p), np.full((20, 30, 3), 40000, np.uint16))
    with pytest.raises(InputError) as e:
        read_image(p, expect="uint16")
    assert str(e.value) == (f"{p}: expected a 16-bit single-channel PNG, got a 16-bit RGB PNG (30x20 px) (hint: write "
                            "it as a 16-bit greyscale PNG (a uint16 array through cv2.imwrite); an 8-bit or colour "
                            "export has lost the values)")
    cv2.imwrite(str(p), np.full((20, 30, 3), 200, np.uint8))  # an 8-bit one: as before
    with pytest.raises(InputError, match=r"got uint8 with shape \(20, 30, 3\)"):
        read_image(p, expect="uint16")
