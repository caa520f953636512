"""Self-contained HTML reports: tables, matplotlib figures and images embedded as base64, a header,
and pages built from a list of :class:`Section` (a report module appends sections; nothing else to change).

Cells: ``None`` and NaN print as an en dash (never ``None``/``nan``); :class:`Raw` marks trusted HTML.
"""
from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

import gtforge
from gtforge.infra.atomic import atomic_write_text

MISSING = "\u2013"  # what an empty cell shows (None, NaN)


class Raw(str):
    """A cell or heading that is already HTML (not escaped)."""


@dataclass
class Section:
    """One ``<h2>`` heading and its body. ``status`` colours the heading (a verdict)."""

    heading: str
    body: str
    status: Literal["pass", "warn", "fail"] | None = None
    anchor: str | None = None


def esc(v: Any) -> str:
    return v if isinstance(v, Raw) else html.escape(str(v))


def fmt_value(v: Any, fmt: str = "{:.4g}") -> str:
    """One value as text: ``None``/NaN -> an en dash, floats through ``fmt``, the rest through ``str``."""
    if v is None:
        return MISSING
    if isinstance(v, (float, np.floating)):
        return MISSING if not math.isfinite(float(v)) else fmt.format(float(v))
    return str(v)


def pct_text(v: Any, decimals: int = 3) -> Any:
    """A share in % as text with ``decimals`` decimals, never rounded onto 0 or 100 when it is not exactly that
    (a coverage of 99.997 % is not "100"): ``> 99.999`` / ``< 0.001`` instead. None/NaN are returned as they are
    (the table shows its dash)."""
    if v is None or not math.isfinite(float(v)):
        return v
    v = float(v)
    text = f"{v:.{decimals}f}"
    step = f"{10.0 ** -decimals:.{decimals}f}"
    if 0.0 < v < 100.0 and float(text) in (0.0, 100.0):
        return f"< {step}" if float(text) == 0.0 else f"> {100.0 - 10.0 ** -decimals:.{decimals}f}"
    return text


def fig_to_png(fig, dpi: int = 100) -> bytes:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def fig_to_img_tag(fig, width: str = "100%", dpi: int = 100, alt: str = "") -> str:
    b64 = base64.b64encode(fig_to_png(fig, dpi)).decode("ascii")
    return f'<img style="max-width:{width}" alt="{html.escape(alt)}" src="data:image/png;base64,{b64}"/>'


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], fmt: str | Sequence[str | None] = "{:.4g}",
          caption: str | None = None, cls: str | None = None) -> str:
    """An HTML table. ``fmt``: one float format, or one per column (``None`` = the default ``{:.4g}``).
    ``cls="kv"``: a key/value table (every cell left-aligned)."""
    fmts = [fmt] * len(headers) if isinstance(fmt, str) else [f or "{:.4g}" for f in fmt]

    def cell(v, k):
        return v if isinstance(v, Raw) else html.escape(fmt_value(v, fmts[k] if k < len(fmts) else "{:.4g}"))

    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{cell(v, k)}</td>" for k, v in enumerate(r)) + "</tr>" for r in rows)
    cap = f"<caption>{esc(caption)}</caption>" if caption else ""
    attr = f' class="{html.escape(cls)}"' if cls else ""
    return f"<table{attr}>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], fmt: str = "{:.4g}") -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt_value(v, fmt) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def verdict_badge(status: Literal["pass", "warn", "fail"], text: str | None = None) -> Raw:
    return Raw(f'<span class="{status}">{html.escape(text or status.upper())}</span>')


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


def header_block(items: Sequence[tuple[str, Any]]) -> str:
    """The page header: a small key/value list (date, gtforge version, inputs)."""
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{esc(fmt_value(v))}</td></tr>" for k, v in items)
    return f'<table class="header">{rows}</table>'


def standard_header(*extra: tuple[str, Any]) -> list[tuple[str, Any]]:
    """``[("written", now), ("gtforge", version)] + extra``."""

    return [("written", now_text()), ("gtforge version", gtforge.__version__), *extra]


def now_text() -> str:
    return _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S %Z")


CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1250px;color:#111}
table{border-collapse:collapse;margin:.6em 0 1.2em}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#eee}td:first-child{text-align:left}table.kv td{text-align:left}\
caption{caption-side:bottom;text-align:left;font-size:.85em;color:#555;padding-top:3px}
table.header{font-size:.9em}table.header th{text-align:left}table.header td{text-align:left;font-family:monospace}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.8em}
h2.pass,span.pass{color:#060}h2.fail,span.fail{color:#b00}h2.warn,span.warn{color:#a55a00}
span.pass,span.fail,span.warn{font-weight:bold}
h2.pass,h2.fail,h2.warn{padding:.3em .5em;border-radius:4px}
h2.pass{background:#e6f4e6}h2.fail{background:#fbe4e4}h2.warn{background:#fdf0dc}
p.note{font-size:.9em;color:#444;max-width:60em}p.warn{color:#a55a00}
figure{display:inline-block;margin:4px 8px 12px 0;vertical-align:top}\
div.maps{display:flex;gap:10px;align-items:flex-start}figcaption{font-size:.85em;color:#333}"""


def write_html(path: str | Path, title: str, sections: Sequence[Section | tuple[str, str]],
               header: Sequence[tuple[str, Any]] | None = None) -> Path:
    """The page: ``title``, the ``header`` block, then every section in order."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    if header:
        parts.append(header_block(header))
    for s in sections:
        if not isinstance(s, Section):
            s = Section(*s)
        cls = f' class="{s.status}"' if s.status else ""
        anchor = f' id="{html.escape(s.anchor)}"' if s.anchor else ""
        parts.append(f"<h2{cls}{anchor}>{esc(s.heading)}</h2>{s.body}")
    parts.append("</body></html>")
    return atomic_write_text(path, "\n".join(parts))


def nice_ceil(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 x 10^k that is >= ``x`` (a readable colour-scale top)."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    k = np.floor(np.log10(x))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        v = float(m * 10 ** k)
        if v >= x * (1 - 1e-9):
            return v
    return float(10 ** (k + 1))
