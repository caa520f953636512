"""Paste the demo's figures into docs/pipeline.md ("Figures on synthetic data"), so that the page shows what the run
printed, never figures copied by hand.

    python scripts/update_demo_figures.py [DEMO_DIR]

DEMO_DIR: a finished ``gtforge demo`` folder (its ``figures.md``); without it the demo runs into a new temporary folder
first (several minutes). The table goes between the ``<!-- demo-figures:begin -->`` and ``<!-- demo-figures:end -->``
markers; nothing else on the page changes.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "pipeline.md"
BEGIN, END = "<!-- demo-figures:begin -->", "<!-- demo-figures:end -->"


def paste(figures: str, page: Path = PAGE) -> None:
    text = page.read_text()
    if BEGIN not in text or END not in text:
        sys.exit(f"{page}: the markers {BEGIN} / {END} are missing")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    page.write_text(f"{head}{BEGIN}\n{figures.strip()}\n{END}{tail}")


def main(argv: list[str]) -> int:
    if argv:
        demo = Path(argv[0])
    else:
        demo = Path(tempfile.mkdtemp(prefix="gtforge-demo-"))
        subprocess.run([sys.executable, "-m", "gtforge.cli", "demo", str(demo)], check=True)
    figures = demo / "figures.md"
    if not figures.is_file():
        sys.exit(f"{figures}: no such file (a demo folder of this gtforge writes it)")
    paste(figures.read_text())
    print(f"{PAGE}: figures from {figures}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
