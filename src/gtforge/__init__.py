"""gtforge: structured-light + ZED -> stereo training data with sub-pixel ground truth."""
from __future__ import annotations

__version__ = "0.1.0"

from gtforge.errors import InputError  # noqa: E402,F401
