"""Dataset file formats: PFM, KITTI uint16 PNG, float32 TIFF, PNG/JPG images, PLY.

Invalid encodings (docs/conventions.md): NaN in memory; PFM ``+inf``; KITTI PNG ``0``; TIFF NaN.
Every writer is atomic.

Encoder settings were chosen by measurement (benchmarks/RESULTS.md, "Output encodings"):
* label PNGs (masks, regions, KITTI disparity; read every epoch, written once): no PNG filter, deflated by
  zlib-ng at level 1 (``encode_label_png``). They decode as fast as OpenCV's fastest-decoding setting (level 1,
  default strategy, no filter), much faster than OpenCV's default, and encode much faster than it; a KITTI PNG is
  0.9 instead of 0.6 MB (zlib-ng's level 1 uses fixed Huffman codes). The PNG container (signature, IHDR, one
  IDAT, IEND) is written here; zlib-ng does the deflate, in blocks of 16 rows each compressed on its own
  (``_deflate_blocks``: 0.3 % larger), so that a view's ``disp_occ`` and ``disp_noc`` share every block without an
  occluded pixel (``write_kitti_disparity_pair``).
* image PNGs (im0/im1 where a scene re-encodes them, imported and synthetic captures, overlays): the PNG filter "Up"
  (each row minus the row above) on every row, deflated by ISA-L at level 1 (``encode_png``): 0.03 s for a 2208 x
  1242 RGB image against OpenCV's 0.08 s; the real ZED Mini image 0.82 MB against OpenCV's 0.92 (the synthetic render
  4.48 against 4.10, Middlebury's im1 0.74 against 0.72). Without ISA-L, OpenCV's encoder.
* float32 TIFF: uncompressed by default (zlib on float depth is slow to encode and to decode, for a 5x smaller
  file); ``compression="zlib"`` for piecewise-constant data such as weights: strips of 64 rows deflated by zlib-ng
  at level 1 (0.12 MB instead of 11 MB; tifffile's own zlib at level 1: 0.06 MB, several times slower).
"""
from __future__ import annotations

import functools
import io
import math
import re
import struct
import sys
from pathlib import Path
from typing import Literal

import cv2
import numba
import numpy as np
import tifffile
from llvmlite import ir as llvm_ir
from numba.extending import intrinsic
from zlib_ng import zlib_ng

from gtforge.errors import InputError, MissingFileError
from gtforge.infra.atomic import atomic_path, atomic_write_buffer, atomic_write_bytes
from gtforge.infra.unbuffered import aligned_buffer

try:  # PNG inflate: ISA-L where its wheel exists (hand-vectorised, faster than zlib-ng), else zlib-ng (same results)
    from isal import isal_zlib as _png_inflate_lib

    _png_deflate_lib = _png_inflate_lib  # image PNGs' deflate (``encode_png``); without ISA-L, OpenCV's
except ImportError:  # pragma: no cover - platforms without an isal wheel
    _png_inflate_lib = zlib_ng
    _png_deflate_lib = None


_LITTLE_ENDIAN = sys.byteorder == "little"


@intrinsic
def _store_bytes(typingctx, arr, i, x):
    """Store integer ``x`` as its bytes (native byte order) in uint8 array ``arr`` from index ``i`` (any alignment):
    one store instead of one per byte."""
    def codegen(context, builder, sig, args):
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        ptr = builder.bitcast(builder.gep(data, [args[1]]), context.get_value_type(sig.args[2]).as_pointer())
        store = builder.store(args[2], ptr)
        store.align = 1
        return context.get_dummy_value()

    return numba.types.void(arr, numba.types.intp, x), codegen


@intrinsic
def _load_u64(typingctx, arr, i):
    """The 8 bytes of uint8 array ``arr`` from index ``i`` as one uint64 (native byte order; any alignment)."""
    def codegen(context, builder, sig, args):
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        load = builder.load(builder.bitcast(builder.gep(data, [args[1]]), llvm_ir.IntType(64).as_pointer()))
        load.align = 1
        return load

    return numba.types.uint64(arr, numba.types.intp), codegen


# ---- PFM ------------------------------------------------------------------------------------
def write_pfm(path: str | Path, disp_px: np.ndarray) -> Path:
    """Write a single-channel float32 PFM (``Pf``, little-endian, rows bottom-to-top); NaN -> +inf."""
    a = np.asarray(disp_px, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"{a.shape=} but expected (H, W)")
    header = f"Pf\n{a.shape[1]} {a.shape[0]}\n-1.0\n".encode("ascii")
    buf = aligned_buffer(len(header) + a.size * 4)  # the file's bytes, written past the page cache (io.unbuffered)
    buf.data[:len(header)] = np.frombuffer(header, np.uint8)
    rows = buf.data[len(header):].view("<f4").reshape(a.shape)  # (unaligned: the header is 18 bytes or so)
    np.copyto(rows, a[::-1])  # bottom-to-top: numpy copies each row as one block, faster than a compiled loop
    _pfm_invalid_to_inf(rows)
    return atomic_write_buffer(path, buf)


@numba.njit(cache=True)
def _pfm_invalid_to_inf(rows):
    """NaN and -inf -> +inf, in place (the copy just made is still in the cache)."""
    H, W = rows.shape
    for v in range(H):
        row = rows[v]
        for u in range(W):
            if not abs(row[u]) < np.float32(np.inf):
                row[u] = np.float32(np.inf)


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM (``Pf`` or the first channel of ``PF``) -> ``(H, W)`` float32, inf/NaN -> NaN."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, None, "a readable PFM file", exc.strerror or str(exc),
                         "check the path, and that this user may read the file") from None
    m = re.match(rb"(P[fF])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if not m:
        raise InputError(path, "header", "'Pf W H scale' PFM header", repr(data[:20]), "is this a PFM file?")
    kind, w, h = m.group(1), int(m.group(2)), int(m.group(3))
    got, hint = repr(m.group(4).decode())[:40], "write the header as 'Pf', 'W H', '-1.0' (one a line), as " \
        "gtforge.io.formats.write_pfm does"
    try:  # the pattern lets through what is no number ('.', '-e', '--1'): a ValueError traceback before
        scale = float(m.group(4))
    except ValueError:
        raise InputError(path, "header", "a PFM scale (a number: < 0 little-endian, > 0 big-endian)", got,
                         hint) from None
    if scale == 0.0 or not math.isfinite(scale):  # its sign is the byte order: 0 gives none (was read as big-endian)
        raise InputError(path, "header", "a non-zero PFM scale (< 0 little-endian, > 0 big-endian)", got, hint)
    ch = 3 if kind == b"PF" else 1
    n = w * h * ch * 4
    body = data[m.end():m.end() + n]
    if len(body) != n:
        raise InputError(path, "data", f"{n} bytes for {w}x{h}x{ch} float32", f"{len(body)} bytes",
                         "the file is truncated")
    a = np.frombuffer(body, dtype="<f4" if scale < 0 else ">f4").reshape(h, w, ch)[..., 0]
    a = np.flipud(a).astype(np.float32)
    return np.where(np.isfinite(a), a, np.nan).astype(np.float32)


# ---- KITTI ----------------------------------------------------------------------------------
# the largest disparity KITTI's uint16 PNG holds (round(d * 256) <= 65535); a larger one is written invalid (0)
KITTI_MAX_DISPARITY_PX = 65535.5 / 256


def _kitti_inputs(disp_px: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(disp_px)
    if d.ndim != 2:
        raise ValueError(f"{d.shape=} but expected (H, W)")
    if mask is not None and np.shape(mask) != d.shape:
        raise ValueError(f"{np.shape(mask)=} but expected {d.shape} (the disparity's shape)")
    m = np.ones(d.shape, bool) if mask is None else np.ascontiguousarray(mask, bool)
    return np.ascontiguousarray(d, dtype=np.float32), m


def write_kitti_disparity(path: str | Path, disp_px: np.ndarray, mask: np.ndarray | None = None) -> Path:
    """KITTI uint16 PNG: ``round(d*256)``; invalid (NaN, inf, <0) and too large (``KITTI_MAX_DISPARITY_PX`` or more)
    -> 0; a valid value that rounds to 0 -> 1.
    ``mask``: only these pixels (e.g. the non-occluded ones, for ``disp_noc``); 0 elsewhere."""
    return write_png16(path, _kitti_quantize(*_kitti_inputs(disp_px, mask)))


def write_kitti_disparity_pair(path_occ: str | Path, path_noc: str | Path, disp_px: np.ndarray,
                               nonoccluded: np.ndarray) -> tuple[Path, Path]:
    """One view's KITTI ``disp_occ`` (every valid pixel) and ``disp_noc`` (the ``nonoccluded`` ones) PNGs, the same
    files as two ``write_kitti_disparity`` calls, byte for byte. The two differ only in rows with an occluded valid
    pixel: each block of ``LABEL_PNG_BLOCK_ROWS`` rows without one is deflated once, for both files, and only those
    rows are made a second time, for ``disp_noc``."""
    occ, same, zero, noc_rows = _kitti_png_rows(*_kitti_inputs(disp_px, nonoccluded))
    h, w = occ.shape[0], (occ.shape[1] - 1) // 2
    occ_blocks = _deflate_blocks(occ, zero)
    noc_blocks, noc_adler, k = [], 1, 0  # (1: the Adler-32 of no data)
    for i, v in enumerate(range(0, h, LABEL_PNG_BLOCK_ROWS)):
        block, differs = occ[v:v + LABEL_PNG_BLOCK_ROWS], ~same[v:v + LABEL_PNG_BLOCK_ROWS]
        if differs.any():
            n_differ = int(np.count_nonzero(differs))
            block = block.copy()
            block[differs] = noc_rows[k:k + n_differ]
            k += n_differ
            noc_blocks.append(_deflate_block(block))
        else:
            noc_blocks.append(occ_blocks[i])
        noc_adler = zlib_ng.adler32(block, noc_adler)
    return (atomic_write_bytes(path_occ, _png_bytes(w, h, 16, occ_blocks, zlib_ng.adler32(occ))),
            atomic_write_bytes(path_noc, _png_bytes(w, h, 16, noc_blocks, noc_adler)))


@numba.njit(cache=True, inline="always")
def _kitti_value(x):
    """round(x * 256) (half to even), at least 1, as an int32; 0 where x is invalid (NaN, inf, < 0) or too large for
    KITTI's 16 bits (round(x * 256) > 65535: x >= 255.998 px, ``KITTI_MAX_DISPARITY_PX``), which a clip to 65535 would
    have turned into a valid label of 255.996 px. ``x``: float32, computed in float32: ``x * 256`` is exact there as in
    float64 (a power of two), so its rounding is the float64 one. Without a branch, so that a loop over a row
    vectorises."""
    r = np.rint(x * np.float32(256.0))
    clipped = min(max(r, np.float32(1.0)), np.float32(65535.0))  # (converted in either case: a finite value)
    return np.int32(clipped) if (x >= np.float32(0.0)) & (r <= np.float32(65535.0)) else np.int32(0)


@numba.njit(cache=True)
def _kitti_quantize(d, mask):
    """``_kitti_value`` of every pixel; 0 outside ``mask``. One pass, instead of the numpy expression's several
    passes and temporaries."""
    H, W = d.shape
    q = np.zeros((H, W), np.uint16)
    for v in range(H):
        for u in range(W):
            if mask[v, u]:
                q[v, u] = np.uint16(_kitti_value(np.float32(d[v, u])))
    return q


@numba.njit(cache=True)
def _kitti_png_rows(d, mask):
    """The PNG rows (filter byte 0, then big-endian uint16) of ``_kitti_quantize(d, all)``, whether each row is the
    same in ``_kitti_quantize(d, mask)``, whether it is all zeros (no valid pixel), and the PNG rows of
    ``_kitti_quantize(d, mask)`` where they are not the same (in row order). Each row is quantised into a buffer
    first, in a loop without stores to the PNG rows that the compiler vectorises."""
    H, W = d.shape
    n = 1 + 2 * W
    occ = np.empty((H, n), np.uint8)
    flat = occ.reshape(-1)
    same = np.ones(H, np.bool_)
    zero = np.empty(H, np.bool_)
    noc = np.empty((H, n), np.uint8)  # (pages only touched for the rows that differ)
    n_noc = 0
    q_row = np.empty(W, np.int32)
    for v in range(H):
        d_row, m_row = d[v], mask[v]
        for u in range(W):
            q_row[u] = _kitti_value(d_row[u])
        differs = nonzero = np.int32(0)
        for u in range(W):
            differs |= q_row[u] & (np.int32(m_row[u]) - 1)  # a valid value outside the mask
            nonzero |= q_row[u]
        zero[v] = nonzero == 0
        flat[v * n] = 0
        for u in range(W):
            _store_bytes(flat, v * n + 1 + 2 * u, _big_endian_u16(q_row[u]))
        if differs:
            same[v] = False
            noc[n_noc, 0] = 0
            for u in range(W):
                _store_bytes(noc[n_noc], 1 + 2 * u, _big_endian_u16(q_row[u] if m_row[u] else np.int32(0)))
            n_noc += 1
    return occ, same, zero, noc[:n_noc]


@numba.njit(inline="always")
def _big_endian_u16(q):
    """uint16 ``q`` (given as int32) as the uint16 whose bytes in memory are ``q``'s big-endian bytes."""
    if _LITTLE_ENDIAN:
        return np.uint16(((q >> 8) | (q << 8)) & 0xFFFF)
    return np.uint16(q)


def read_kitti_disparity(path: str | Path) -> np.ndarray:
    q = read_image(path, expect="uint16")
    d = q.astype(np.float32) / 256.0
    d[q == 0] = np.nan
    return d


def write_png16(path: str | Path, a: np.ndarray) -> Path:
    """Single-channel uint16 PNG with the label settings (fast to decode)."""
    return write_label_png(path, np.asarray(a, np.uint16))


# rows of a label PNG deflated together (``_deflate_blocks``): 16 rows of a 2208 px KITTI PNG are 71 kB
LABEL_PNG_BLOCK_ROWS = 16


def _deflate_blocks(rows: np.ndarray, zero: np.ndarray | None = None) -> list[bytes]:
    """PNG image data (``rows``: ``(H, 1 + row bytes)`` uint8, filter bytes included) as raw deflate by zlib-ng at level
    1, in blocks of ``LABEL_PNG_BLOCK_ROWS`` rows (``_deflate_block`` each): their concatenation is one valid deflate
    stream, and a block is the same bytes wherever the same rows occur. ``zero``: whether each row is all zeros (filter
    byte included), when known: a block of such rows is taken from ``_deflated_zeros``."""
    n = LABEL_PNG_BLOCK_ROWS
    return [_deflated_zeros(rows[v:v + n].nbytes) if zero is not None and zero[v:v + n].all() else
            _deflate_block(rows[v:v + n]) for v in range(0, rows.shape[0], n)]


@functools.lru_cache(maxsize=16)
def _deflated_zeros(n_bytes: int) -> bytes:
    """``_deflate_block`` of ``n_bytes`` zero bytes, made once a size: the rows above and below the ground truth of
    every KITTI image."""
    return _deflate_block(np.zeros(n_bytes, np.uint8))


def _deflate_block(rows: np.ndarray) -> bytes:
    """``rows`` deflated on their own (zlib-ng, level 1, raw deflate) and ended by a full flush: byte-aligned, referring
    to no earlier data, not final."""
    c = zlib_ng.compressobj(1, zlib_ng.DEFLATED, -15)
    return c.compress(rows) + c.flush(zlib_ng.Z_FULL_FLUSH)


def _png_bytes(w: int, h: int, bit_depth: int, blocks: list[bytes], adler: int) -> bytes:
    """A greyscale PNG: signature, IHDR, one IDAT holding the zlib stream of ``blocks`` (``_deflate_blocks`` of the
    rows) whose Adler-32 is ``adler``, IEND. Joined once (the IDAT's CRC taken over its parts)."""
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, 0, 0, 0, 0)  # grey, deflate, adaptive filtering, no interlace
    head = b"IDAT\x78\x01"  # the zlib header: deflate, 32 kB window, fastest level
    tail = b"\x03\x00" + struct.pack(">I", adler)  # an empty final block (fixed Huffman codes), the Adler-32
    crc = zlib_ng.crc32(head)
    for block in blocks:
        crc = zlib_ng.crc32(block, crc)
    crc = zlib_ng.crc32(tail, crc)
    n_idat = len(head) - 4 + sum(len(block) for block in blocks) + len(tail)
    return b"".join((PNG_SIGNATURE, _png_chunk(b"IHDR", ihdr), struct.pack(">I", n_idat), head, *blocks, tail,
                     struct.pack(">I", crc), _PNG_IEND))


_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk: no data, its CRC


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk: its length, type, data and CRC (of type and data)."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib_ng.crc32(data, zlib_ng.crc32(kind)))


def encode_label_png(a: np.ndarray) -> bytes:
    """A single-channel uint8 or uint16 image as PNG bytes: filter type 0 (none) on every row, deflated by zlib-ng at
    level 1 in blocks of rows (``_deflate_blocks``; the label encoding, see the module docstring). Any PNG reader
    decodes it."""
    a = np.asarray(a)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16) or 0 in a.shape:
        raise ValueError(f"{a.shape=}, {a.dtype=} but expected a non-empty (H, W) uint8 or uint16 label image")
    h, w = a.shape
    rows = np.empty((h, 1 + w * a.itemsize), np.uint8)
    rows[:, 0] = 0  # each row's filter type (0: none)
    rows[:, 1:] = a.astype(a.dtype.newbyteorder(">"), copy=False).view(np.uint8).reshape(h, -1)  # PNG is big-endian
    return _png_bytes(w, h, 8 * a.itemsize, _deflate_blocks(rows), zlib_ng.adler32(rows))


def write_label_png(path: str | Path, a: np.ndarray) -> Path:
    """A single-channel uint8 or uint16 label image (mask, region labels, KITTI disparity) as PNG, encoded
    fast to write and to decode (``encode_label_png``)."""
    return atomic_write_bytes(path, encode_label_png(a))


# ---- TIFF -----------------------------------------------------------------------------------
def write_tiff_float(path: str | Path, a: np.ndarray, compression: Literal["none", "zlib"] = "none") -> Path:
    """float32 TIFF (depth in mm or weights); NaN stays NaN. ``compression="zlib"`` (deflate by zlib-ng, level 1)
    pays for piecewise-constant data only (see the module docstring); every TIFF reader decodes both."""
    a = np.ascontiguousarray(a, np.float32)
    if compression == "none":  # tifffile's file for this shape, with a's bytes in it, written past the page cache
        head, tail = _tiff_layout(a.shape, a.dtype.str)
        buf = aligned_buffer(len(head) + a.nbytes + len(tail))
        d = buf.data
        d[:len(head)] = np.frombuffer(head, np.uint8)
        np.copyto(d[len(head):len(head) + a.nbytes].view(a.dtype).reshape(a.shape), a)
        d[len(head) + a.nbytes:] = np.frombuffer(tail, np.uint8)
        return atomic_write_buffer(path, buf)
    with atomic_path(path) as tmp:  # strips of 64 rows deflated by zlib-ng at level 1 (faster than tifffile's zlib)
        n = TIFF_ROWS_PER_STRIP
        strips = (zlib_ng.compress(a[v:v + n], 1) for v in range(0, a.shape[0], n))
        tifffile.imwrite(tmp, strips, shape=a.shape, dtype=a.dtype, compression="zlib", rowsperstrip=n)
    return Path(path)


TIFF_ROWS_PER_STRIP = 64


@functools.lru_cache(maxsize=8)
def _tiff_layout(shape: tuple[int, ...], dtype: str) -> tuple[bytes, bytes]:
    """``(bytes before, bytes after)`` the pixel data in the uncompressed TIFF ``tifffile.imwrite`` writes for an
    array of this shape and dtype: it depends on nothing else (no date, no software tag; tests/io/test_formats.py checks
    that the two give the same file), and its pixels are one contiguous run of the array's bytes in memory order."""
    f = io.BytesIO()
    a = np.zeros(shape, dtype)
    tifffile.imwrite(f, a)
    data = f.getvalue()
    with tifffile.TiffFile(io.BytesIO(data)) as t:
        page = t.pages[0]
        offsets, counts = page.dataoffsets, page.databytecounts
    start = offsets[0]
    if sum(counts) != a.nbytes or any(o != start + sum(counts[:i]) for i, o in enumerate(offsets)):
        raise AssertionError(f"tifffile {tifffile.__version__} lays out an uncompressed {shape} {dtype} TIFF's pixels "
                             "in more than one run")
    return data[:start], data[start + a.nbytes:]


# ---- 8-bit images ---------------------------------------------------------------------------
def encode_png(a: np.ndarray) -> bytes | None:
    """An 8-bit grey ``(H, W)`` or RGB ``(H, W, 3)`` image as PNG bytes: filter type 2 ("Up") on every row, deflated by
    ISA-L at level 1 (see the module docstring). None where ISA-L is not installed (``write_image`` then uses OpenCV)
    or for any other array."""
    a = np.asarray(a)
    if _png_deflate_lib is None or a.dtype != np.uint8 or 0 in a.shape or not (
            a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        return None
    h, w = a.shape[:2]
    flat = a.reshape(h, -1)
    rows = np.empty((h, 1 + flat.shape[1]), np.uint8)
    rows[:, 0] = 2  # each row's filter type: Up (the first row's "row above" is zeros: its bytes as they are)
    rows[0, 1:] = flat[0]
    np.subtract(flat[1:], flat[:-1], out=rows[1:, 1:])  # modulo 256, as the filter is defined
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0 if a.ndim == 2 else 2, 0, 0, 0)  # grey or RGB, deflate, filtered rows,
    # no interlace
    return b"".join((PNG_SIGNATURE, _png_chunk(b"IHDR", ihdr), _png_chunk(b"IDAT", _png_deflate_lib.compress(rows, 1)),
                     _PNG_IEND))


def write_image(path: str | Path, img: np.ndarray) -> Path:
    """Write an RGB (H, W, 3) or grey (H, W) uint8 image; format from the suffix (PNG, JPG, BMP). A PNG is
    ``encode_png``'s where it can be (OpenCV's otherwise)."""
    a = np.asarray(img)
    if (Path(path).suffix or ".png").lower() == ".png":
        data = encode_png(a)
        if data is not None:
            return atomic_write_bytes(path, data)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(Path(path).suffix or ".png", a)
    if not ok:
        raise RuntimeError(f"image encode failed for {path}")
    return atomic_write_bytes(path, buf.tobytes())


def read_image(path: str | Path, expect: str | None = None, field: str | None = None,
               data: bytes | memoryview | None = None, rows: int | None = None) -> np.ndarray:
    """Read PNG/JPG/BMP/TIFF -> RGB ``(H, W, 3)`` uint8, grey ``(H, W)``, or uint16 as stored.

    ``data``: the file's bytes, already read (``path`` then names it in errors). Truncated or corrupt files raise
    ``InputError`` (OpenCV would silently return part of the image). ``rows``: only the image's first rows are
    wanted (``decode_png`` then stops inflating there; other formats are decoded whole and cut).
    """
    path = Path(path)
    if data is None and not path.is_file():
        raise MissingFileError(path, field, "an image file", hint="check the capture folder / session.yaml")
    try:
        if path.suffix.lower() in (".tif", ".tiff"):
            a = tifffile.imread(path if data is None else io.BytesIO(data))
        else:
            data = path.read_bytes() if data is None else data
            a = decode_png(data, rows) if data[:8] == PNG_SIGNATURE else None
            if a is None:  # not a PNG, or one of the PNG variants decode_png leaves to imageio
                import imageio.v3 as iio  # (here: imageio's import, 8-15 ms, is for these files only)

                a = iio.imread(bytes(data), extension=path.suffix or None)  # (bytes: data may be a memoryview)
        if rows is not None:
            a = a[:rows]
    except Exception as exc:  # imageio raises several types for corrupt data
        raise InputError(path, field, "a readable image", f"a decode error ({type(exc).__name__}: "
                         f"{str(exc).splitlines()[0][:80] if str(exc) else ''})",
                         "the file may be truncated or not an image") from None
    a = np.asarray(a)
    if a.ndim == 3 and a.shape[2] == 4:
        a = a[..., :3]
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if expect == "uint16" and a.dtype != np.uint16:
        got = f"{a.dtype} with shape {a.shape}"
        if data is not None and bytes(data[:8]) == PNG_SIGNATURE and len(data) >= 26 and data[24] == 16:
            # a 16-bit colour PNG, which imageio (Pillow) reduced to 8 bits: named as the file is
            got = f"a 16-bit {_PNG_COLOURS.get(data[25], 'colour')} PNG ({a.shape[1]}x{a.shape[0]} px)"
        raise InputError(path, field, "a 16-bit single-channel PNG", got,
                         "write it as a 16-bit greyscale PNG (a uint16 array through cv2.imwrite); an 8-bit or colour "
                         "export has lost the values")
    if expect == "uint8" and a.dtype != np.uint8:
        raise InputError(path, field, "an 8-bit image", f"{a.dtype}", "convert it to 8-bit PNG")
    return np.ascontiguousarray(a)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> samples per pixel (grey, RGB, grey + alpha, RGBA)
_PNG_COLOURS = {2: "RGB", 4: "grey + alpha", 6: "RGBA"}


def decode_png(data: bytes, rows: int | None = None) -> np.ndarray | None:
    """Decode the common PNG variants: 8-bit grey, grey + alpha, RGB or RGBA and 16-bit grey, not interlaced,
    without a ``tRNS`` chunk. Returns what imageio returns for them (``(H, W)`` or ``(H, W, C)``, uint8 or native
    uint16), or None for any other variant (palette, < 8 bits, 16-bit colour, interlaced, tRNS): the caller
    decodes those with imageio. ``rows``: decode the first ``rows`` rows only (``(rows, W, ...)``): the stream is
    inflated only as far as they need, so its end and checksum are not checked then (the chunks' CRCs are).

    Why not imageio/Pillow or OpenCV for these: they inflate with the system zlib, where most of a decode's time
    goes; ISA-L (``isal``) and zlib-ng (the fallback where isal has no wheel) inflate much faster, and the row filters
    are undone in one compiled pass (benchmarks/RESULTS.md, "profile_scene" and "Figures from code comments"). Every
    chunk's CRC, the zlib stream's end and checksum, the data size and each row's filter type are checked: a
    truncated or corrupt file raises ``ValueError``.
    """
    view = memoryview(data)
    if bytes(view[:8]) != PNG_SIGNATURE:
        raise ValueError("not a PNG file (bad signature)")
    pos, header, idat = 8, None, []
    size, crc32, unpack_from = len(view), zlib_ng.crc32, struct.unpack_from
    while True:
        if pos + 12 > size:
            raise ValueError("truncated PNG: the file ends before its IEND chunk")
        n, kind = unpack_from(">I4s", view, pos)
        end = pos + 8 + n  # the chunk's data ends here, its CRC follows
        if end + 4 > size:
            raise ValueError(f"truncated PNG: the {kind!r} chunk runs past the end of the file")
        if crc32(view[pos + 4:end]) != unpack_from(">I", view, end)[0]:  # (the CRC covers the type and the data)
            raise ValueError(f"corrupt PNG: CRC mismatch in the {kind.decode('latin-1')} chunk")
        if kind == b"IDAT":
            idat.append(view[pos + 8:end])
        elif kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", view[pos + 8:end])
        elif kind == b"tRNS":
            return None  # transparency imageio turns into alpha
        elif kind == b"IEND":
            break
        pos = end + 4
    if header is None or not idat:
        raise ValueError("corrupt PNG: no IHDR or no IDAT chunk")
    w, h, bits, colour, compression, filtering, interlace = header
    if not (bits == 8 or (bits == 16 and colour == 0)) or colour not in _PNG_CHANNELS or interlace != 0 \
            or compression != 0 or filtering != 0:
        return None  # (Pillow, and so imageio, reduces 16-bit colour to 8 bits: left to it, unchanged)
    ch = _PNG_CHANNELS[colour]
    bpp = ch * bits // 8  # bytes per pixel: the Sub/Average/Paeth filters' left neighbour
    size = h * (1 + w * bpp)  # each row: its filter type byte, then its bytes
    part = rows is not None and 0 <= rows < h
    inflater = _png_inflate_lib.decompressobj()
    want = rows * (1 + w * bpp) if part else size
    raw = inflater.decompress(b"".join(idat), want) if want else b""  # (a max_length of 0 means no limit)
    if part:
        if len(raw) != want:
            raise ValueError(f"corrupt PNG: the image data ends before row {rows} (truncated)")
        h = rows
    elif not inflater.eof or len(raw) != size:
        why = "truncated, or more data than its IHDR's size" if not inflater.eof else "less data than its IHDR's size"
        raise ValueError(f"corrupt PNG: the image data does not inflate to {size} bytes ({why})")
    out = np.empty((h, w * bpp), np.uint8)
    bad_row = _png_unfilter(np.frombuffer(raw, np.uint8), out, bpp)
    if bad_row >= 0:
        raise ValueError(f"corrupt PNG: unknown filter type on row {bad_row}")
    a = out if bits == 8 else out.view(">u2").astype(np.uint16)
    return a.reshape(h, w) if ch == 1 else a.reshape(h, w, ch)


@numba.njit(cache=True, nogil=True)
def _png_unfilter(raw, out, bpp):
    """Undo PNG's per-row filters (0 none, 1 Sub, 2 Up, 3 Average, 4 Paeth) from ``raw`` (each row: its filter type,
    then the filtered bytes) into ``out`` ``(H, row bytes)``, ``bpp`` 1 to 4. Returns the first row with an unknown
    filter type, or -1. Bytes left of the row and the row above the first are zeros."""
    H, n = out.shape
    zeros = np.zeros(n, np.uint8)
    v = 0
    while v < H:
        src = raw[v * (n + 1) + 1:(v + 1) * (n + 1)]
        cur = out[v]
        up = out[v - 1] if v > 0 else zeros
        kind = raw[v * (n + 1)]
        if kind == 1 and bpp > 1 and _SWAR_SUB and n >= 8:  # two Sub rows side by side (they need no row above;
            # one byte a pixel: the byte loop below is as fast)
            pair = v + 1 < H and raw[(v + 1) * (n + 1)] == 1
            _unfilter_sub_rows_bpp(raw, out, v, v + 1 if pair else v, bpp)
            v += 2 if pair else 1
            continue
        if kind == 0:
            cur[:] = src
        elif kind == 2:
            for i in range(n):
                cur[i] = (np.int32(src[i]) + up[i]) & 255
        elif kind == 1:  # the filter type and bpp as constants: each combination compiles to its own loop
            _unfilter_left_row_bpp(1, src, up, cur, bpp)
        elif kind == 3:
            _unfilter_left_row_bpp(3, src, up, cur, bpp)
        elif kind == 4:
            _unfilter_left_row_bpp(4, src, up, cur, bpp)
        else:
            return v
        v += 1
    return -1


# The Sub filter 8 bytes at a time (``_unfilter_sub_rows``) reads the bytes as little-endian 64-bit words
_SWAR_SUB = _LITTLE_ENDIAN
_LOW7 = np.uint64(0x7F7F7F7F7F7F7F7F)
_HIGH1 = np.uint64(0x8080808080808080)


@numba.njit(inline="always")
def _add_bytes(x, y):
    """The eight bytes of ``x`` and ``y`` added each on its own, modulo 256 (no carry into the next byte)."""
    return ((x & _LOW7) + (y & _LOW7)) ^ ((x ^ y) & _HIGH1)


@numba.njit(inline="always")
def _unfilter_sub_rows_bpp(raw, out, v0, v1, bpp):
    if bpp == 2:
        _unfilter_sub_rows(raw, out, v0, v1, 2)
    elif bpp == 3:
        _unfilter_sub_rows(raw, out, v0, v1, 3)
    else:
        _unfilter_sub_rows(raw, out, v0, v1, 4)


@numba.njit(inline="always")
def _unfilter_sub_rows(raw, out, v0, v1, bpp):
    """Rows ``v0`` and ``v1`` (Sub-filtered; the same row twice for one alone) 8 bytes at a time: each 64-bit word's
    running sums over its own bytes with stride ``bpp`` (log2 steps of shifted byte-wise adds), plus the last ``bpp``
    bytes of the word before, repeated with period ``bpp``. A byte-by-byte loop is one chain of dependent adds per
    channel and one store per byte; two rows interleave two independent chains."""
    n = out.shape[1]
    flat = out.reshape(-1)
    b0, b1 = v0 * (n + 1) + 1, v1 * (n + 1) + 1
    o0, o1 = v0 * n, v1 * n
    shift = np.uint64(8 * bpp)
    last = np.uint64(64 - 8 * bpp)
    w0 = w1 = np.uint64(0)  # the previous output word of each row: zeros left of the row
    i = 0
    while i + 8 <= n:
        x0 = _load_u64(raw, b0 + i)
        x1 = _load_u64(raw, b1 + i)
        s = shift
        while s < 64:
            x0 = _add_bytes(x0, x0 << s)
            x1 = _add_bytes(x1, x1 << s)
            s += s
        t0, t1 = w0 >> last, w1 >> last
        c0, c1 = t0, t1
        s = shift
        while s < 64:
            c0 |= t0 << s
            c1 |= t1 << s
            s += shift
        w0, w1 = _add_bytes(x0, c0), _add_bytes(x1, c1)
        _store_bytes(flat, o0 + i, w0)
        _store_bytes(flat, o1 + i, w1)
        i += 8
    for j in range(i, n):  # the row's last n % 8 bytes
        flat[o0 + j] = (np.int32(raw[b0 + j]) + flat[o0 + j - bpp]) & 255
        flat[o1 + j] = (np.int32(raw[b1 + j]) + flat[o1 + j - bpp]) & 255


@numba.njit(inline="always")
def _unfilter_left_row_bpp(kind, src, up, cur, bpp):
    if bpp == 1:
        _unfilter_left_row(kind, src, up, cur, 1)
    elif bpp == 2:
        _unfilter_left_row(kind, src, up, cur, 2)
    elif bpp == 3:
        _unfilter_left_row(kind, src, up, cur, 3)
    else:
        _unfilter_left_row(kind, src, up, cur, 4)


@numba.njit(inline="always")
def _unfilter_left_row(kind, src, up, cur, bpp):
    """One row of the filters that use the left neighbour (Sub, Average, Paeth). Each channel's left and upper-left
    values are carried in registers (a0..a3, c0..c3) instead of being read back from the row just written: the
    store-to-load round trip was the loop's critical path (benchmarks/RESULTS.md, "Figures from code comments")."""
    a0 = a1 = a2 = a3 = np.int32(0)
    c0 = c1 = c2 = c3 = np.int32(0)
    for p in range(0, cur.shape[0], bpp):
        b = np.int32(up[p])
        a0 = (np.int32(src[p]) + _png_predictor(kind, a0, b, c0)) & 255
        cur[p], c0 = a0, b
        if bpp > 1:
            b = np.int32(up[p + 1])
            a1 = (np.int32(src[p + 1]) + _png_predictor(kind, a1, b, c1)) & 255
            cur[p + 1], c1 = a1, b
        if bpp > 2:
            b = np.int32(up[p + 2])
            a2 = (np.int32(src[p + 2]) + _png_predictor(kind, a2, b, c2)) & 255
            cur[p + 2], c2 = a2, b
        if bpp > 3:
            b = np.int32(up[p + 3])
            a3 = (np.int32(src[p + 3]) + _png_predictor(kind, a3, b, c3)) & 255
            cur[p + 3], c3 = a3, b


@numba.njit(inline="always")
def _png_predictor(kind, a, b, c):
    """The predictor of filter ``kind`` from the left (a), upper (b) and upper-left (c) bytes."""
    if kind == 1:
        return a
    if kind == 3:
        return (a + b) >> 1
    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
    return a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)


# ---- PLY ------------------------------------------------------------------------------------
def write_ply(path: str | Path, pts_mm: np.ndarray, colors_rgb01: np.ndarray | None = None) -> Path:
    """Point cloud through Open3D (binary PLY), atomically."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(pts_mm, np.float64).reshape(-1, 3)))
    if colors_rgb01 is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors_rgb01, np.float64).reshape(-1, 3), 0, 1))
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
            raise RuntimeError(f"Open3D failed to write {path}")
    return Path(path)


def read_ply_points(path: str | Path) -> np.ndarray:
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)
