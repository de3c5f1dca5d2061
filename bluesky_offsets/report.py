"""One self-contained HTML report per analysis: images inlined, openable offline."""

from __future__ import annotations

import base64
import html
import json
import time
from collections.abc import Mapping, Sequence
from pathlib import Path


def _img(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode()
    return f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"/>' \
           f"<figcaption>{html.escape(alt)}</figcaption></figure>"


def _table(rows: Sequence[Mapping], columns: Sequence[str] | None = None, fmt: str = "{:.4g}") -> str:
    if not rows:
        return "<p>(none)</p>"
    columns = list(columns or rows[0].keys())

    def cell(v):
        if isinstance(v, float):
            return fmt.format(v)
        if isinstance(v, (dict, list)):
            return html.escape(json.dumps(v, default=str)[:200])
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c, ''))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


_CSS = """
body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;font-size:.9em;margin:.6em 0}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:right}th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
figure{margin:1em 0}img{max-width:100%}figcaption{font-size:.85em;color:#555}
.verdict{font-size:1.15em;padding:.6em 1em;background:#eef6ee;border-left:4px solid #3a3}
.warn{background:#fff5e6;border-left-color:#e90}code{background:#f5f5f5;padding:0 .2em}
"""


def write_report(path: str | Path, *, title: str, sections: Sequence[tuple[str, str]]) -> Path:
    """Write a report from ``(heading, html body)`` sections."""
    path = Path(path)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>",
             f"<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by bluesky-offsets.</p>"]
    for heading, body in sections:
        parts.append(f"<h2>{html.escape(heading)}</h2>{body}")
    parts.append("</body></html>")
    path.write_text("\n".join(parts), encoding="utf-8")
    return path


def image(path: Path, alt: str) -> str:
    return _img(path, alt)


def table(rows, columns=None, fmt: str = "{:.4g}") -> str:
    return _table(rows, columns, fmt)


def verdict(text: str, warn: bool = False) -> str:
    return f"<p class='verdict{' warn' if warn else ''}'>{html.escape(text)}</p>"
