"""Report documents: self-contained HTML (PNG figures inlined as base64 data URIs), Markdown
(figures as files next to it) and CSV tables."""

from __future__ import annotations

import base64
import html
import math
from pathlib import Path

from magail_sumo.evaluation.realism import METRIC_FIELDS
from magail_sumo.outputs import inside, inside_dir, write_bytes

from .figures import Figure


def fmt(v: object) -> str:
    if isinstance(v, float):
        return "n/a" if math.isnan(v) else f"{v:.4g}"
    return str(v)


def html_table(header: list[str], rows: list[list[object]], cls: str) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(c))}</td>" for c in r) + "</tr>"
                   for r in rows)
    return (f'<div class="table-wrap"><table class="{cls}"><thead><tr>{head}</tr></thead>'
            f'<tbody>{body}</tbody></table></div>')


def md_table(header: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def img_tag(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


#: a page that fits any width: tables scroll inside their own box (never the page), long
#: words break, images scale down
CSS = """body{font-family:sans-serif;margin:2em;max-width:1400px;overflow-wrap:anywhere}
.table-wrap{max-width:100%;overflow-x:auto;margin:1em 0}
table{border-collapse:collapse;font-size:13px}
th,td{border:1px solid #bbb;padding:3px 8px;text-align:right;overflow-wrap:normal}
th{background:#eee;vertical-align:bottom}td:first-child,th:first-child{text-align:left}
img{max-width:100%;height:auto;display:block;margin:0.5em 0}.errors li{color:#a00}
.note{color:#555;font-size:13px}"""


class Document:
    """Sections accumulated into HTML and Markdown at once."""

    def __init__(self, title: str, img_dir: Path) -> None:
        self.title = title
        self.html: list[str] = [f"<h1>{html.escape(title)}</h1>"]
        self.md: list[str] = [f"# {title}"]
        self.img_dir = img_dir
        self._n = 0
        self.css: list[str] = []  #: extra style sheets
        self.scripts: list[str] = []  #: inline scripts run at the end of the page

    def raw(self, fragment: str, md: str) -> None:
        """An HTML fragment (trusted: built by the report itself) and its Markdown stand-in."""
        self.html.append(fragment)
        self.md.append(md)

    def heading(self, text: str, level: int = 2) -> None:
        self.html.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.md.append("#" * level + " " + text)

    def para(self, text: str) -> None:
        self.html.append(f"<p>{html.escape(text)}</p>")
        self.md.append(text)

    def table(self, header: list[str], rows: list[list[object]], cls: str) -> None:
        self.html.append(html_table(header, rows, cls))
        self.md.append(md_table(header, rows))

    def note(self, text: str) -> None:
        """A paragraph set apart as an explanation (smaller, grey)."""
        self.html.append(f'<p class="note">{html.escape(text)}</p>')
        self.md.append(f"*{text}*")

    def image(self, figure: "bytes | Figure", name: str, alt: str) -> None:
        """A figure: inlined in the HTML, written as ``img_dir/NN_name.png`` for the Markdown
        and, for a :class:`~.figures.Figure`, as ``NN_name.svg`` beside it (a vector copy for
        papers) (:class:`~magail_sumo.outputs.OutputError` when ``img_dir`` or a file leads
        out of the report folder, ``img_dir``'s parent, through a symbolic link)."""
        img_dir = inside_dir(self.img_dir.parent, self.img_dir.name)
        png = figure if isinstance(figure, bytes) else figure.png
        self._n += 1
        fname = f"{self._n:02d}_{name}.png"
        write_bytes(inside(img_dir, fname), png)
        if not isinstance(figure, bytes):
            write_bytes(inside(img_dir, f"{self._n:02d}_{name}.svg"), figure.svg)
        self.html.append(img_tag(png, alt))
        self.md.append(f"![{alt}]({self.img_dir.name}/{fname})")

    def errors(self, lines: list[str]) -> None:
        items = "".join(f"<li>{html.escape(e)}</li>" for e in lines)
        self.html.append(f'<ul class="errors">{items}</ul>')
        self.md.append("\n".join(f"- {e}" for e in lines))

    def write(self, html_path: Path, md_path: Path) -> None:
        page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>"
                f"{html.escape(self.title)}</title><style>{CSS}{''.join(self.css)}</style></head>"
                "<body>" + "\n".join(self.html)
                + "".join(f"<script>{js}</script>" for js in self.scripts) + "</body></html>\n")
        write_bytes(html_path, page.encode("utf-8"))  # atomic: the old file or the new one
        write_bytes(md_path, ("\n\n".join(self.md) + "\n").encode("utf-8"))


REALISM_FIELDS = [f for f in METRIC_FIELDS if f.endswith("_likelihood")]
