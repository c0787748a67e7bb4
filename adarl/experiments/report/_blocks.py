"""A report as a list of small blocks (heading, paragraph, code, table, image), rendered to Markdown and HTML, and
the CSV text each table and figure writes beside it.

The report's sections build blocks; this module alone knows the output formats, so a section never writes
Markdown by hand. Private module of :mod:`adarl.experiments.report`.
"""

from __future__ import annotations

import csv
import html
import io
from dataclasses import dataclass, field

__all__ = [
    "Heading",
    "Paragraph",
    "Code",
    "Table",
    "Image",
    "Bold",
    "Block",
    "render_markdown",
    "render_html",
    "csv_text",
]


@dataclass(frozen=True)
class Heading:
    level: int
    text: str


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Code:
    text: str
    language: str = "bash"


@dataclass(frozen=True)
class Bold:
    """A part of a table cell set in bold: a cell may be a list of parts (``["ours: ", Bold("1.0"), " · paper"]``)."""

    text: str


@dataclass(frozen=True)
class Table:
    header: list[str]
    rows: list[list]  # a cell: a value, or a list of parts (str or Bold) to bold a part of it
    bold: list[tuple[int, int]] = field(default_factory=list)  # (row, column) cells to set in bold


def _parts(cell, bold, plain) -> str:
    """A cell's text, its Bold parts through ``bold`` and the rest through ``plain``."""
    if isinstance(cell, list):
        return "".join(bold(p.text) if isinstance(p, Bold) else plain(str(p)) for p in cell)
    return plain(str(cell))


@dataclass(frozen=True)
class Image:
    path: str  # relative to the report folder
    alt: str


Block = Heading | Paragraph | Code | Table | Image


def _md_table(t: Table) -> list[str]:
    rows = [[_parts(c, lambda x: f"**{x}**", str) for c in r] for r in t.rows]
    for i, j in t.bold:
        rows[i][j] = f"**{rows[i][j]}**"
    out = ["| " + " | ".join(t.header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(t.header) - 1)) + "|"]
    return out + ["| " + " | ".join(r) + " |" for r in rows]


def render_markdown(blocks: list[Block]) -> str:
    lines: list[str] = []
    for b in blocks:
        if isinstance(b, Heading):
            lines += ["#" * b.level + " " + b.text, ""]
        elif isinstance(b, Paragraph):
            lines += [b.text, ""]
        elif isinstance(b, Code):
            lines += [f"```{b.language}", b.text, "```", ""]
        elif isinstance(b, Table):
            lines += _md_table(b) + [""]
        elif isinstance(b, Image):
            lines += [f"![{b.alt}]({b.path})", ""]
        else:
            raise TypeError(f"not a report block: {b!r}")
    return "\n".join(lines)


def render_html(blocks: list[Block]) -> str:
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>adarl report</title><style>"
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto}table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}td:first-child{text-align:left}"
        "img{max-width:100%}</style></head><body>"
    ]
    for b in blocks:
        if isinstance(b, Heading):
            parts.append(f"<h{b.level}>{html.escape(b.text)}</h{b.level}>")
        elif isinstance(b, Paragraph):
            parts.append(f"<p>{html.escape(b.text)}</p>")
        elif isinstance(b, Code):
            parts.append(f"<pre><code>{html.escape(b.text)}</code></pre>")
        elif isinstance(b, Table):
            bold = set(b.bold)
            parts.append("<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in b.header) + "</tr>")
            for i, r in enumerate(b.rows):
                cells = [_parts(c, lambda x: f"<b>{html.escape(x)}</b>", html.escape) for c in r]
                cells = [f"<b>{c}</b>" if (i, j) in bold else c for j, c in enumerate(cells)]
                parts.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
            parts.append("</table>")
        elif isinstance(b, Image):
            parts.append(f"<p><img src='{html.escape(b.path)}' alt='{html.escape(b.alt)}'></p>")
        else:
            raise TypeError(f"not a report block: {b!r}")
    return "\n".join(parts) + "\n</body></html>\n"


def csv_text(rows: list[list], header: list[str]) -> str:
    """``rows`` under ``header`` as CSV text (the data file beside a table or figure)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()
