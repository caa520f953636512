"""The dataset certificate ``gtforge run`` writes (``certificate.json``; its page is ``index.html``,
``reports.certificate``): how good the labels are and why to believe it, every figure with the file and field it was
read from and a link to the stage's own report."""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from gtforge.core.schema import GTModel, VersionedFile

Verdict = Literal["PASS", "WARN", "FAIL"]


class CertFigure(GTModel):
    """One figure: ``value`` (and ``sigma``) exactly as ``source_file``'s ``source_field`` holds it (a dotted path;
    None for a figure derived from several fields, which ``derivation`` then describes)."""
    name: str
    value: float | int | str | bool | None
    unit: str = ""
    sigma: float | None = None
    status: str | None = None  # PASS/FAIL, a scale term's status ...
    source_file: str  # relative to the run's folder
    source_field: str | None = None
    derivation: str = ""
    link: str | None = None  # the stage's own report, relative to the run's folder


class CertSection(GTModel):
    title: str
    verdict: Verdict | None = None
    figures: list[CertFigure] = Field(default_factory=list)
    notes: list[str] = Field(default_factory=list)
    link: str | None = None


class CertStage(GTModel):
    stage: str
    status: Literal["done", "not applicable"]
    verdict: Verdict | None = None
    reasons: list[str] = Field(default_factory=list)


class Certificate(VersionedFile):
    KIND: ClassVar[str] = "dataset certificate (certificate.json from gtforge run)"
    gtforge_version: str
    created: str
    session_dir: str
    verdict: Verdict
    verdict_reasons: list[str] = Field(default_factory=list)
    stages: list[CertStage]
    sections: list[CertSection]
    scenes_built: list[str] = Field(default_factory=list)
    scenes_flagged: dict[str, list[str]] = Field(default_factory=dict)
    scenes_quarantined: list[str] = Field(default_factory=list)
    scenes_failed: dict[str, str] = Field(default_factory=dict)
    layouts: list[str] = Field(default_factory=list)  # training-ready layouts written, relative to the run's folder
    splits: dict[str, int] = Field(default_factory=dict)  # split -> number of scenes
    inputs_blake3: dict[str, str] = Field(default_factory=dict)  # every session file a stage read
    inputs_digest: str = ""  # BLAKE3 of the sorted "path hash" lines of inputs_blake3
