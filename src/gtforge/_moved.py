"""Old module paths that still import, for one release after the package was laid out in layers (round 3).

``import gtforge.camera`` gives a stand-in module whose attributes are read from ``gtforge.core.camera`` (and, for a
module that was split, from each new home in turn), with a DeprecationWarning naming the new path. New code imports
the new path; docs/architecture.md lists the layers.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings

# old dotted path -> new homes, searched in order for each attribute
MOVED: dict[str, tuple[str, ...]] = {
    "gtforge.io.atomic": ("gtforge.infra.atomic",),
    "gtforge.io.unbuffered": ("gtforge.infra.unbuffered",),
    "gtforge.io.digest": ("gtforge.infra.digest",),
    "gtforge.scheduling": ("gtforge.infra.scheduling",),
    "gtforge.pool_preload": ("gtforge.infra.pool_preload",),
    **{f"gtforge.{m}": (f"gtforge.core.{m}",) for m in (
        "schema", "camera", "lens", "geometry", "board", "targets", "coverage", "reproject", "reproject_reference",
        "uncertainty", "metrics", "shapefit", "fruit_size")},
    # split modules: an attribute is looked up in each new home in turn
    "gtforge.rectification": ("gtforge.core.rectification", "gtforge.io.zed_rectification",
                              "gtforge.reports.rectification"),
    "gtforge.selfcal": ("gtforge.core.selfcal", "gtforge.io.zed_rectification"),
    "gtforge.gauges": ("gtforge.core.gauges", "gtforge.validate"),
    "gtforge.targets": ("gtforge.core.targets", "gtforge.core.target_detection", "gtforge.calibrate",
                        "gtforge.synthetic"),
}


class _Forward(types.ModuleType):
    def __getattr__(self, name: str):
        for home in self.__gtforge_homes__:
            mod = importlib.import_module(home)
            if hasattr(mod, name):
                return getattr(mod, name)
        raise AttributeError(f"module {self.__name__!r} (moved to {', '.join(self.__gtforge_homes__)}) has no "
                             f"attribute {name!r}")

    def __dir__(self):
        return sorted({n for h in self.__gtforge_homes__ for n in dir(importlib.import_module(h))})


class _Loader(importlib.abc.Loader):
    def create_module(self, spec):
        mod = _Forward(spec.name)
        mod.__gtforge_homes__ = MOVED[spec.name]
        return mod

    def exec_module(self, module):
        warnings.warn(f"{module.__name__} moved to {', '.join(module.__gtforge_homes__)}; the old path goes in the "
                      "next release", DeprecationWarning, stacklevel=2)


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if fullname in MOVED:
            return importlib.machinery.ModuleSpec(fullname, _Loader())
        return None


def install() -> None:
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.append(_Finder())
