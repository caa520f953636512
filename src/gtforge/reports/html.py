"""Self-contained HTML reports (tables + matplotlib figures embedded as base64 PNG)."""
from __future__ import annotations

import base64
import html
import io
from pathlib import Path
from typing import Any, Sequence

from gtforge.io.atomic import atomic_write_text


def fig_to_img_tag(fig, width: str = "100%") -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    b64 = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img style="max-width:{width}" src="data:image/png;base64,{b64}"/>'


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], fmt: str = "{:.4g}") -> str:
    def cell(v):
        if isinstance(v, float):
            return fmt.format(v)
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], fmt: str = "{:.4g}") -> str:
    def cell(v):
        return fmt.format(v) if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#eee}.pass{color:#070;font-weight:bold}.fail{color:#b00;font-weight:bold}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:2em}.warn{color:#a60}"""


def write_html(path: str | Path, title: str, sections: Sequence[tuple[str, str]]) -> Path:
    """``sections``: (heading, inner HTML) pairs."""
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    for heading, body in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    parts.append("</body></html>")
    return atomic_write_text(path, "\n".join(parts))
