"""Base for every file gtforge writes: pydantic, ``extra="forbid"``, ``schema_version``."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any, ClassVar, TypeVar

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, PlainSerializer, ValidationError, field_validator

from gtforge.errors import InputError
from gtforge.infra.atomic import atomic_write_text

M = TypeVar("M", bound="GTModel")

# libyaml's parser where PyYAML was built with it (its wheels are): the same values as PyYAML's own parser (the
# constructor that makes them is the same Python code), about 7x faster; a calibration file 5 -> 0.7 ms, read by the
# command and again by every build worker's warm-up
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_yaml(text: str) -> Any:
    """``yaml.safe_load(text)``, with libyaml's parser where there is one."""
    return yaml.load(text, Loader=_YAML_LOADER)


def parse_error(exc: Exception, what: str = "YAML", text: str | None = None) -> tuple[str, str]:
    """``(got, hint)`` of an InputError for a YAML or JSON ``text`` that did not parse: the problem with its line and
    column (1-based, as editors count), and a hint that fits it (a tab, a text that ends too soon, else the place)."""
    mark = getattr(exc, "problem_mark", None)  # yaml.MarkedYAMLError (PyYAML's and libyaml's parsers)
    if mark is not None:
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        line, col, index = mark.line + 1, mark.column + 1, mark.index
    elif isinstance(exc, json.JSONDecodeError):
        problem, line, col, index, text = exc.msg, exc.lineno, exc.colno, exc.pos, exc.doc
    else:
        return f"a parse error ({str(exc).splitlines()[0]})", f"fix the {what}, or is the file truncated?"
    got = f"a parse error at line {line}, column {col}: {problem}"
    if "tab" in problem.lower() or "'\\t'" in problem:
        hint = f"indent with spaces, not tabs (line {line})"
    elif text is not None and index >= len(text.rstrip()):
        hint = f"the text ends before its {what} does: is the file truncated, or a bracket or quote left open?"
    elif what == "JSON":
        hint = f"fix the JSON at line {line} (a comma, quote or bracket out of place is the usual cause)"
    else:
        hint = f"fix the YAML at line {line} (an indent or a ':' out of place is the usual cause)"
    return got, hint


class GTModel(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class VersionedFile(GTModel):
    """A top-level file model. Subclasses set ``SCHEMA_VERSION``."""

    SCHEMA_VERSION: ClassVar[int] = 1
    KIND: ClassVar[str] = "gtforge file"  # what a person calls this file, in error messages
    schema_version: int = 1

    @field_validator("schema_version")
    @classmethod
    def _check_version(cls, v: int) -> int:
        if v != cls.SCHEMA_VERSION:
            raise ValueError(f"schema_version {v} is not supported (this gtforge reads {cls.SCHEMA_VERSION})")
        return v

    @classmethod
    def kind_with_article(cls) -> str:
        """``KIND`` after "a" or "an", as a message says "expected a calibration file"."""
        return ("an " if cls.KIND[:1].lower() in "aeiou" else "a ") + cls.KIND

    # ---- I/O -------------------------------------------------------------------------------
    def write(self, path: str | Path) -> Path:
        path = Path(path)
        data = self.model_dump(mode="json")
        if path.suffix.lower() == ".json":
            text = json.dumps(data, indent=2)
        else:
            text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)
        atomic_write_text(path, text)
        return path

    @classmethod
    def read(cls: type[M], path: str | Path) -> M:
        path = Path(path)
        if path.is_dir():
            raise InputError(path, None, cls.kind_with_article(), "a folder", "give the file's path")
        if not path.is_file():
            raise InputError(path, None, cls.kind_with_article(), "no such file", "check the path")
        try:
            text = path.read_text(encoding="utf-8-sig")  # (a byte-order mark, as some editors write, is dropped)
        except UnicodeDecodeError as exc:
            raise InputError(path, None, f"{cls.kind_with_article()}, a YAML/JSON text file",
                             f"binary data (byte 0x{exc.object[exc.start]:02x} at offset {exc.start} is not UTF-8 "
                             "text)",
                             "is this the right file?") from None
        try:
            data = json.loads(text) if path.suffix.lower() == ".json" else load_yaml(text)
        except (yaml.YAMLError, json.JSONDecodeError) as exc:
            raise InputError(path, None, "valid YAML/JSON", *parse_error(
                exc, "JSON" if path.suffix.lower() == ".json" else "YAML", text)) from None
        return cls.from_dict(data, path)

    @classmethod
    def from_dict(cls: type[M], data: Any, path: str | Path | None = None) -> M:
        if not isinstance(data, dict):
            got = "an empty file" if data is None else f"a YAML/JSON {type(data).__name__}, not a mapping"
            raise InputError(path, None, f"{cls.kind_with_article()} (a YAML/JSON mapping)", got,
                             "is this the right file?")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise pydantic_to_input_error(exc, path, cls.KIND, cls.model_fields) from None


# the problems one message lists (a file of another kind has a hundred: the first ones say enough)
MAX_PROBLEMS = 8


def pydantic_to_input_error(exc: ValidationError, path: str | Path | None, what: str,
                            fields_known: Any = ()) -> InputError:
    """Every problem of a file in one line (a file with several is fixed in one round; past ``MAX_PROBLEMS``, how
    many more), each naming its field; a missing field says ``missing``, never the whole mapping it is missing from.
    ``fields_known``: the file's top-level field names, for a misspelt one's hint."""
    errs = exc.errors()
    version = [e for e in errs if tuple(e.get("loc", ())) == ("schema_version",)]
    errs = version or errs  # a file of another schema: its other differences follow from that one

    def actual(err) -> str:
        if err.get("type") == "missing":
            return "missing"
        a = repr(err.get("input"))
        return a if len(a) <= 80 else a[:77] + "..."

    def field(err) -> str:
        return ".".join(str(p) for p in err.get("loc", ()))

    def misspelt(err) -> str | None:
        """``did you mean ...`` for an unknown top-level field close to a known one (``zed_rectifed``)."""
        loc = err.get("loc", ())
        if err.get("type") != "extra_forbidden" or len(loc) != 1:
            return None
        import difflib

        close = difflib.get_close_matches(str(loc[0]), list(fields_known), n=1, cutoff=0.8)
        return f"did you mean {close[0]}?" if close else None

    def what_to_do(err) -> str | None:
        """The hint where no field name is close: a file gtforge writes is written again by its command (``what``
        names it: "... (from gtforge calibrate)"); a file a person writes gets a missing field added, an unknown one
        removed, a wrong value corrected (its message says what to give)."""
        m = re.search(r"from (gtforge [a-z-]+)", what)
        if m:
            return (f"write it again with {m.group(1)} (was it edited by hand, or written by another gtforge "
                    "version?)")
        name = field(err) or "the field"
        if err.get("type") == "missing":
            return f"add {name}"
        if err.get("type") == "extra_forbidden":
            return f"remove {name}: not a field of {what}"
        return f"correct {name} in the file, then rerun"

    if len(errs) == 1:
        err = errs[0]
        return InputError(path, field(err) or None, f"a valid {what} ({err.get('msg')})", actual(err),
                          misspelt(err) or what_to_do(err))
    top = [e for e in errs if len(e.get("loc", ())) == 1]
    missing = [field(e) for e in top if e.get("type") == "missing"]
    extra = [field(e) for e in top if e.get("type") == "extra_forbidden"]
    # (judged on the top level: a file of another kind may have nested problems too, a list of poses' fields)
    if extra and len(missing) + len(extra) >= 4 and len(missing) >= 2:
        # none of the fields it should have, others instead: another kind of file, not one to fix field by field
        return InputError(path, None, f"a {what}", f"a file of another kind (its fields: {', '.join(extra[:6])}"
                          f"{' ...' if len(extra) > 6 else ''}; missing: {', '.join(missing[:6])}"
                          f"{' ...' if len(missing) > 6 else ''})", f"give the {what} itself (docs/pipeline.md)")
    fields = list(dict.fromkeys(field(e) or "(top level)" for e in errs))
    hints = [h for h in map(misspelt, errs) if h]
    shown = errs[:MAX_PROBLEMS]
    return InputError(path, ", ".join(fields[:MAX_PROBLEMS]) + (" ..." if len(fields) > MAX_PROBLEMS else ""),
                      f"a valid {what}",
                      f"{len(errs)} problems: " + "; ".join(f"{field(e) or '(top level)'}: {e.get('msg')} "
                                                           f"(got {actual(e)})" for e in shown)
                      + (f"; +{len(errs) - len(shown)} more" if len(errs) > len(shown) else ""),
                      "; ".join(hints[:3] + ["fix them all, then rerun"]))


def matrix4_field(v: Any) -> list[list[float]]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"shape {a.shape}, expected (4, 4)")
    if not np.all(np.isfinite(a)):
        raise ValueError("non-finite value")
    R = a[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or abs(np.linalg.det(R) - 1) > 1e-5
            or np.abs(a[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise ValueError("not a rigid transform (rotation part not orthonormal or last row not 0 0 0 1)")
    return a.tolist()


def matrix4_array(v: Any) -> np.ndarray:
    a = np.array(matrix4_field(v), dtype=np.float64)
    a.setflags(write=False)  # a pose held by a model is read-only: change it through the model (with_extrinsic)
    return a


# A 4x4 rigid transform held as a float64 array, written as a list of rows (the same file as ``matrix4_field``'s).
Matrix4 = Annotated[np.ndarray, BeforeValidator(matrix4_array),
                    PlainSerializer(lambda a: np.asarray(a, np.float64).tolist(), return_type=list)]
