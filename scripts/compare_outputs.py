"""Are two runs' outputs the same? Every file byte for byte, except what records when and where a run happened.

    python scripts/compare_outputs.py RUN_A RUN_B

RUN_A and RUN_B are two output folders of the same commands (scripts/reference_outputs.sh) made by two versions of
gtforge, e.g. before and after a restructuring (docs/architecture.md, "Checking that a change keeps the outputs").
Images, PFM/TIFF maps, point clouds and arrays must be byte-identical. JSON and YAML files are compared as data after
dropping the fields that record time (``time_s``, ``time_ms``, ``time_*``, ``created``, ``hashed_at_ns``,
``mtime_ns``) and the hashes of files that hold such fields (``*_sha256``: a calibration file records its solve time),
with each run's folder replaced by ``RUN`` (in a ``gtforge run``'s run_state.json, the digests of the run's own
outputs too: they are compared as files); text files (HTML, Markdown, CSV, logs) after the same replacement, with
dates, clock times and durations masked, table columns headed by a time blanked, and embedded matplotlib SVGs compared
without their drawing date and random ids. Exit status 0: the same; 1: a difference (each one listed).
"""
from __future__ import annotations

import argparse
import base64
import hashlib
import json
import re
import sys
from pathlib import Path

import yaml

# fields that record when or how long; hashes of files that themselves hold such fields (a calibration's solve time)
TIME_KEY = re.compile(r"^(time_s|time_ms|time_\w+|created|hashed_at_ns|mtime_ns|\w+_sha256)$")
TEXT_SUFFIXES = {".html", ".md", ".csv", ".txt", ".log"}
DATA_SUFFIXES = {".json", ".yaml", ".yml"}
MASKS = [
    (re.compile(r"\d{4}-\d{2}-\d{2}[ T]\d{2}:\d{2}(:\d{2}(\.\d+)?)?([+-]\d{2}:\d{2})?"), "<DATE>"),
    (re.compile(r"\b\d+(\.\d+)? ?(ms|s)\b(?= *(<|\)|,|;|$|\||->|per\b))"), "<DURATION>"),
    (re.compile(r"\b\d+(\.\d+)? ms/frame"), "<DURATION>/frame"),
    (re.compile(r"(time \((?:s|ms)\)</th><td>)[^<]*"), r"\1<DURATION>"),
    (re.compile(r"\b(in|took|done in) \d+(\.\d+)? s\b"), r"\1 <DURATION>"),
]
SVG_URI = re.compile(r"data:image/svg\+xml;base64,([A-Za-z0-9+/=]+)")
SVG_DATE = re.compile(rb"<dc:date>[^<]*</dc:date>")
SVG_ID = re.compile(rb"\b[mp][0-9a-f]{8,12}\b")  # matplotlib's random ids of markers and clip paths


def _svg_key(b64: str) -> str:
    """An embedded matplotlib SVG without what changes from run to run: its date and its random ids (numbered in
    order of appearance instead)."""
    svg = SVG_DATE.sub(b"", base64.b64decode(b64))
    ids: dict[bytes, bytes] = {}
    svg = SVG_ID.sub(lambda m: ids.setdefault(m.group(0), b"id%d" % len(ids)), svg)
    return hashlib.sha256(svg).hexdigest()


def _drop_time(x):
    if isinstance(x, dict):
        return {k: _drop_time(v) for k, v in x.items() if not TIME_KEY.match(str(k))}
    if isinstance(x, list):
        return [_drop_time(v) for v in x]
    return x


def _text(path: Path, root: Path) -> str:
    s = path.read_text(errors="replace")
    # the absolute form first: a relative folder is part of it, and replaced first would leave "/abs/path/RUN". Only
    # where it stands as a path: a short relative name ("r2") also occurs inside words and embedded base64 images,
    # which replaced there differed from the other run's (a folder "rI4") though the files were the same
    for r in sorted({str(root), str(root.resolve())}, key=len, reverse=True):
        # (a sentence may end on the folder: "dataset /tmp/out." is a path, "/tmp/out.png" is not)
        s = re.sub(r"(?<![\w/.+=-])" + re.escape(r) + r"(?![\w+=-]|\.[\w+=-])", "RUN", s)
    return s


def _without_output_digests(state: dict) -> dict:
    """A ``gtforge run``'s run_state.json without the digests of the run's own outputs (``out/...`` in the stages'
    inputs and outputs, ``RUN/...`` in its hash cache): a calibration file records its solve time, so its digest
    differs between two identical runs; the files themselves are compared one by one."""
    def stage(rec):
        return {**rec, **{k: {f: "<FILE>" if f.startswith("out/") else d for f, d in rec[k].items()}
                          for k in ("inputs", "outputs") if isinstance(rec.get(k), dict)}}

    return {**state, "stages": {n: stage(r) for n, r in state.get("stages", {}).items()},
            "hashes": {f: "<FILE>" if f.startswith("RUN/") else h for f, h in state.get("hashes", {}).items()}}


def _data(path: Path, root: Path):
    s = _text(path, root)
    data = _drop_time(json.loads(s) if path.suffix == ".json" else yaml.safe_load(s))
    return _without_output_digests(data) if path.name == "run_state.json" and isinstance(data, dict) else data


TABLE = re.compile(r"<table>.*?</table>", re.S)
ROW = re.compile(r"<tr>(.*?)</tr>", re.S)
CELL = re.compile(r"<t[hd][^>]*>.*?</t[hd]>", re.S)


def _html_tables_without_time(s: str) -> str:
    """Each HTML table's cells under a header that names a time (``time (ms)``) blanked."""
    def table(m):
        t = m.group(0)
        head = ROW.search(t)
        if head is None:
            return t
        drop = {i for i, c in enumerate(CELL.findall(head.group(1))) if "time" in c.lower()}
        if not drop:
            return t
        return ROW.sub(lambda r: "<tr>" + "".join("<td></td>" if i in drop else c for i, c in
                                                    enumerate(CELL.findall(r.group(1)))) + "</tr>", t)
    return TABLE.sub(table, s)


def _masked(s: str) -> str:
    # an embedded matplotlib SVG carries the time it was drawn and random ids: compared without them
    s = SVG_URI.sub(lambda m: "data:image/svg+xml;sha256," + _svg_key(m.group(1)), s)
    s = _html_tables_without_time(s)
    for rx, sub in MASKS:
        s = rx.sub(sub, s)
    return s


def _table_without_time(s: str, sep: str) -> str:
    """A CSV's (``sep`` ",") or Markdown table's (``sep`` "|") columns whose header names a time blanked."""
    out, drop = [], set()
    for ln in s.splitlines():
        cells = ln.split(sep)
        if sep == "|" and not ln.startswith("|"):
            drop = set()
        elif not drop or (sep == "|" and any("time" in c.lower() for c in cells)):
            drop = {i for i, c in enumerate(cells) if "time" in c.lower()} or drop
        out.append(sep.join("" if i in drop else c for i, c in enumerate(cells)) if drop else ln)
    return "\n".join(out)


def compare(a: Path, b: Path) -> list[str]:
    files_a = {p.relative_to(a) for p in a.rglob("*") if p.is_file() or p.is_symlink()}
    files_b = {p.relative_to(b) for p in b.rglob("*") if p.is_file() or p.is_symlink()}
    diffs = [f"only in {a}: {p}" for p in sorted(files_a - files_b)]
    diffs += [f"only in {b}: {p}" for p in sorted(files_b - files_a)]
    for rel in sorted(files_a & files_b):
        pa, pb = a / rel, b / rel
        if pa.is_symlink() or pb.is_symlink():
            ta = str(Path(pa.readlink())) if pa.is_symlink() else None
            tb = str(Path(pb.readlink())) if pb.is_symlink() else None
            if (ta and ta.replace(str(a), "RUN")) != (tb and tb.replace(str(b), "RUN")):
                diffs.append(f"{rel}: links differ ({ta} vs {tb})")
            continue
        if pa.read_bytes() == pb.read_bytes():
            continue
        suffix = pa.suffix.lower()
        if suffix in DATA_SUFFIXES:
            if _data(pa, a) != _data(pb, b):
                diffs.append(f"{rel}: data differ beyond time fields")
        elif suffix in TEXT_SUFFIXES:
            ta, tb = _text(pa, a), _text(pb, b)
            if suffix in (".csv", ".md", ".log"):
                sep = "," if suffix == ".csv" else "|"
                ta, tb = _table_without_time(ta, sep), _table_without_time(tb, sep)
            ta, tb = _masked(ta), _masked(tb)
            if ta != tb:
                la, lb = ta.splitlines(), tb.splitlines()
                first = next((i for i, (x, y) in enumerate(zip(la, lb)) if x != y), min(len(la), len(lb)))
                diffs.append(f"{rel}: text differs at line {first + 1}: "
                             f"{(la[first] if first < len(la) else '<end>')[:160]!r} vs "
                             f"{(lb[first] if first < len(lb) else '<end>')[:160]!r}")
        else:
            diffs.append(f"{rel}: bytes differ")
    return diffs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    args = ap.parse_args(argv)
    diffs = compare(args.run_a, args.run_b)
    n = sum(1 for p in args.run_a.rglob("*") if p.is_file())
    for d in diffs:
        print(d)
    print(f"{n} files compared: {'the same' if not diffs else f'{len(diffs)} difference(s)'}")
    return 1 if diffs else 0


if __name__ == "__main__":
    sys.exit(main())
