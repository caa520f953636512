"""docs/conventions.md's pose names, checked on the package's source and on the tests, the benchmarks and the
scripts: a rigid transform is named ``T_<dst>_from_<src>``; never a bare ``T`` (or ``T0``, ``Tb``, ``T_zw`` ...),
``pose``, ``w2c``, ``c2w`` or ``extrinsics``."""
from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "gtforge"
# the project's other Python: the tests (this file included), the benchmarks and the scripts
OTHER_FOLDERS = ("tests", "benchmarks", "scripts")

POSE_NAME = re.compile(r"^T_[a-z0-9]+(?:_[a-z0-9]+)*_from_[a-z0-9]+(?:_[a-z0-9]+)*$")
# what reads as a transform's name: T alone, or T followed by a digit, an underscore or a short abbreviation (Tb, Tcw)
LOOKS_LIKE_A_POSE = re.compile(r"^T(?:[0-9_].*|[a-z]{1,3})?$")
FORBIDDEN = {"pose", "w2c", "c2w", "extrinsics"}
# OpenCV's stereo translation (``cv2.stereoRectify``'s ``R, T``), a 3-vector in mm, kept under OpenCV's letter
ALLOWED = {"T_mm"}


def bad_pose_names(source: str) -> list[tuple[int, str]]:
    """``(line, name)`` of every variable, argument, keyword or attribute set in ``source`` whose name breaks the
    rule; names of functions (``invert_T``, ``T_from_rotvec``), classes and imports, and ``TypeVar``s, are not
    transforms and pass."""
    tree = ast.parse(source)
    defined = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}
    defined |= {(a.asname or a.name).split(".")[0] for n in ast.walk(tree)
                  if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names}
    type_vars = {t.id for n in ast.walk(tree) if isinstance(n, ast.Assign) and isinstance(n.value, ast.Call)
                 and getattr(n.value.func, "id", None) == "TypeVar" for t in n.targets if isinstance(t, ast.Name)}
    calls = {id(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    found = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Name) and id(n) not in calls:
            name = n.id
        elif isinstance(n, ast.arg):
            name = n.arg
        elif isinstance(n, ast.keyword) and n.arg:
            name = n.arg
        elif isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store):
            name = n.attr
        else:
            continue
        if name in defined or name in type_vars or name in ALLOWED:
            continue
        if name in FORBIDDEN or (LOOKS_LIKE_A_POSE.match(name) and not POSE_NAME.match(name)):
            found.append((n.lineno, name))
    return sorted(set(found))


def test_every_transform_in_the_package_is_named_dst_from_src():
    bad = [f"{p.relative_to(SRC.parent)}:{line}: {name}" for p in sorted(SRC.rglob("*.py"))
           for line, name in bad_pose_names(p.read_text(encoding="utf-8"))]
    assert not bad, "names that break docs/conventions.md 'Poses':\n" + "\n".join(bad)


def test_every_transform_in_the_tests_benchmarks_and_scripts_is_named_dst_from_src():
    files = {folder: sorted((ROOT / folder).rglob("*.py")) for folder in OTHER_FOLDERS}
    assert all(files.values()) and Path(__file__).resolve() in files["tests"], {k: len(v) for k, v in files.items()}
    bad = [f"{p.relative_to(ROOT)}:{line}: {name}" for paths in files.values() for p in paths
           for line, name in bad_pose_names(p.read_text(encoding="utf-8"))]
    assert not bad, "names that break docs/conventions.md 'Poses':\n" + "\n".join(bad)


def test_the_check_sees_each_kind_of_bad_name():
    source = '''
from typing import TypeVar
from rich.text import Text
U = TypeVar("U")
def invert_T(T_dst_from_src): return T_dst_from_src
def f(T0, pose, T_zed_from_mech):
    Tb = invert_T(T0)
    T_zw = T_zed_from_mech @ Tb
    self.T = T_zw
    g(extrinsics=1, T_mm=2)
    T_mech_from_board_new = T_zed_from_mech
    return Text(T)
'''
    assert bad_pose_names(source) == [(6, "T0"), (6, "pose"), (7, "T0"), (7, "Tb"), (8, "T_zw"), (8, "Tb"),
                                      (9, "T"), (9, "T_zw"), (10, "extrinsics"), (12, "T")]
