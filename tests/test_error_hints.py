"""docs/conventions.md "Errors", checked on the package's source: every ``InputError`` it raises carries a hint (what
to do about it). An AST walk finds each call that constructs ``InputError``, ``MissingFileError`` or any class of
the package that subclasses them, and each must pass its hint: the ``hint`` keyword or the positional argument in
``hint``'s place, and not the literal ``None``. A hint passed through a variable, a call or ``**kwargs`` counts as
given (its value is computed elsewhere). A subclass whose ``__init__`` takes no ``hint`` (``SchedulerLost``) words
its own: the check is then on the ``super().__init__(...)`` in it."""
from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "gtforge"
BASE = "InputError"


@dataclass
class ErrorClass:
    name: str
    hint_pos: int | None  # index of ``hint`` among the positional arguments (self not counted); None: no hint param
    takes_hint: bool  # a ``hint`` parameter (positional or keyword-only) or ``**kwargs``


def _signature(init: ast.FunctionDef) -> tuple[int | None, bool]:
    positional = [a.arg for a in init.args.posonlyargs + init.args.args][1:]  # without self
    if "hint" in positional:
        return positional.index("hint"), True
    keyword_only = [a.arg for a in init.args.kwonlyargs]
    return None, "hint" in keyword_only or init.args.kwarg is not None


def _base_names(cls: ast.ClassDef) -> list[str]:
    return [b.id if isinstance(b, ast.Name) else b.attr for b in cls.bases if isinstance(b, (ast.Name, ast.Attribute))]


def error_classes(trees: dict[str, ast.Module]) -> dict[str, ErrorClass]:
    """``InputError`` and every class in ``trees`` that subclasses it (directly or not), by name, each with where its
    constructor takes the hint (inherited from its base when it defines no ``__init__``)."""
    classes = [n for tree in trees.values() for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]
    found: dict[str, ErrorClass] = {}
    for cls in classes:
        if cls.name == BASE:
            init = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
            found[BASE] = ErrorClass(BASE, *_signature(init))
    assert BASE in found, f"no class {BASE} in the sources"
    grew = True
    while grew:
        grew = False
        for cls in classes:
            if cls.name in found:
                continue
            parent = next((found[b] for b in _base_names(cls) if b in found), None)
            if parent is None:
                continue
            init = next((n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"), None)
            hint_pos, takes_hint = _signature(init) if init else (parent.hint_pos, parent.takes_hint)
            found[cls.name] = ErrorClass(cls.name, hint_pos, takes_hint)
            grew = True
    return found


def _is_none(node: ast.expr) -> bool:
    return isinstance(node, ast.Constant) and node.value is None


def _has_hint(call: ast.Call, cls: ErrorClass) -> bool:
    for kw in call.keywords:
        if kw.arg is None:  # **kwargs: the hint may be in it
            return True
        if kw.arg == "hint":
            return not _is_none(kw.value)
    if any(isinstance(a, ast.Starred) for a in call.args):  # *args: the hint may be in it
        return True
    return cls.hint_pos is not None and len(call.args) > cls.hint_pos and not _is_none(call.args[cls.hint_pos])


def _aliases(tree: ast.Module, classes: dict[str, ErrorClass]) -> dict[str, ErrorClass]:
    """The names this module calls the error classes by: their own, and any ``import ... as`` other name."""
    names = dict(classes)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            for a in node.names:
                if a.name in classes and a.asname:
                    names[a.asname] = classes[a.name]
    return names


def calls_without_hint(trees: dict[str, ast.Module]) -> list[str]:
    """``file:line: Class(...)`` of every construction of an error class with no hint, and of every ``super().__init__``
    without one in a subclass that takes no hint of its callers."""
    classes = error_classes(trees)
    bad = []
    for rel, tree in trees.items():
        names = _aliases(tree, classes)
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and node.name in classes and not classes[node.name].takes_hint:
                parent = next(classes[b] for b in _base_names(node) if b in classes)
                for call in ast.walk(node):
                    if (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)
                            and call.func.attr == "__init__" and isinstance(call.func.value, ast.Call)
                            and getattr(call.func.value.func, "id", None) == "super" and not _has_hint(call, parent)):
                        bad.append(f"{rel}:{call.lineno}: super().__init__ in {node.name}")
            if not isinstance(node, ast.Call):
                continue
            func = node.func
            name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None
            cls = names.get(name)
            if cls is None or not cls.takes_hint:  # no hint parameter: the class words its own (checked above)
                continue
            if not _has_hint(node, cls):
                bad.append(f"{rel}:{node.lineno}: {name}(...)")
    return sorted(bad, key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def _source_trees() -> dict[str, ast.Module]:
    return {str(p.relative_to(SRC.parent)): ast.parse(p.read_text(encoding="utf-8"), str(p))
            for p in sorted(SRC.rglob("*.py"))}


def test_every_input_error_the_package_raises_has_a_hint():
    bad = calls_without_hint(_source_trees())
    assert not bad, ("InputError constructions without a hint (docs/conventions.md 'Errors': say what to do: the "
                     "option to change, the command that writes the file, the doc that explains it):\n"
                     + "\n".join(bad))


def test_the_check_knows_the_package_error_classes():
    classes = error_classes(_source_trees())
    assert {"InputError", "MissingFileError", "SchedulerLost"} <= set(classes)
    assert classes["InputError"].hint_pos == classes["MissingFileError"].hint_pos == 4
    assert not classes["SchedulerLost"].takes_hint


def test_the_check_sees_each_kind_of_missing_hint():
    source = '''
from gtforge.errors import InputError, MissingFileError as Missing
from gtforge import errors
class InputError(ValueError):
    def __init__(self, file, field, expected, actual, hint=None): ...
class NotThere(MissingFileError):
    pass
class Wrapped(InputError):
    def __init__(self, what):
        super().__init__(None, "x", "a", what)
class WrappedWithHint(InputError):
    def __init__(self, what):
        super().__init__(None, "x", "a", what, "do this")
class MissingFileError(InputError):
    def __init__(self, file, field, expected, actual="no such file", hint=None):
        super().__init__(file, field, expected, actual, hint)
raise InputError("f", "k", "a", "b")
raise InputError("f", "k", "a", "b", None)
raise InputError("f", "k", "a", "b", hint=None)
raise InputError("f", "k", "a", "b", "run calibrate")
raise InputError("f", "k", "a", "b", hint=the_hint)
raise InputError(*args)
raise InputError("f", "k", "a", "b", **more)
raise Missing("f", "k", "a")
raise Missing("f", "k", "a", hint="run align-depth")
raise errors.MissingFileError("f", "k", "a", "gone")
raise NotThere("f", "k", "a")
raise Wrapped("b")
'''
    bad = calls_without_hint({"m.py": ast.parse(source)})
    assert bad == ["m.py:10: super().__init__ in Wrapped", "m.py:17: InputError(...)", "m.py:18: InputError(...)",
                   "m.py:19: InputError(...)", "m.py:24: Missing(...)", "m.py:26: MissingFileError(...)",
                   "m.py:27: NotThere(...)"]
