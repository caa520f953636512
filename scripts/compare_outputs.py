"""Are two runs' outputs the same? Every file byte for byte, except what records when and where a run happened.

    python scripts/compare_outputs.py RUN_A RUN_B

RUN_A and RUN_B are two output folders of the same command (``gtforge demo``, ``gtforge synth`` + stages) made by two
versions of gtforge, e.g. before and after a restructuring (docs/architecture.md, "Checking that a change keeps the
outputs"). Images, PFM/TIFF maps, point clouds and arrays must be byte-identical. JSON and YAML files are compared as
data after dropping the fields that record time (``time_s``, ``time_ms``, ``time_*_s``, ``hashed_at_ns``, ``mtime_ns``)
and replacing each run's folder by ``RUN``; text files (HTML, Markdown, CSV, TXT) after the same replacement and with
dates, clock times and durations masked. Exit status 0: the same; 1: a difference (each one listed).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import yaml

TIME_KEY = re.compile(r"^(time_s|time_ms|time_\w+_s|hashed_at_ns|mtime_ns)$")
TEXT_SUFFIXES = {".html", ".md", ".csv", ".txt", ".log"}
DATA_SUFFIXES = {".json", ".yaml", ".yml"}
MASKS = [
    (re.compile(r"\d{4}-\d{2}-\d{2}[ T]\d{2}:\d{2}(:\d{2}(\.\d+)?)?"), "<DATE>"),
    (re.compile(r"\b\d+(\.\d+)? ?(ms|s)\b(?= *(<|\)|,|;|$|\|))"), "<DURATION>"),
]


def _drop_time(x):
    if isinstance(x, dict):
        return {k: _drop_time(v) for k, v in x.items() if not TIME_KEY.match(str(k))}
    if isinstance(x, list):
        return [_drop_time(v) for v in x]
    return x


def _text(path: Path, root: Path) -> str:
    s = path.read_text(errors="replace")
    for r in {str(root), str(root.resolve())}:
        s = s.replace(r, "RUN")
    return s


def _data(path: Path, root: Path):
    s = _text(path, root)
    return _drop_time(json.loads(s) if path.suffix == ".json" else yaml.safe_load(s))


def _masked(s: str) -> str:
    for rx, sub in MASKS:
        s = rx.sub(sub, s)
    return s


def _csv_without_time(s: str) -> str:
    """A CSV's columns whose header names a time (``time_ms`` ...) blanked."""
    lines = s.splitlines()
    if not lines:
        return s
    head = lines[0].split(",")
    drop = {i for i, h in enumerate(head) if TIME_KEY.match(h.strip())}
    return "\n".join(",".join("" if i in drop else c for i, c in enumerate(ln.split(","))) for ln in lines)


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
            if suffix == ".csv":
                ta, tb = _csv_without_time(ta), _csv_without_time(tb)
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
