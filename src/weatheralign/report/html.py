"""Markdown -> one self-contained HTML page (tables, figures embedded as data URIs, inline style, no network)."""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

import markdown

STYLE = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:0.9em}th,td{border:1px solid #bbb;padding:3px 7px}
th{background:#eee}td{text-align:right}td:first-child{text-align:left}img{max-width:100%}
code{background:#f4f4f4;padding:0 3px}"""


def _embed(match: re.Match, base: Path) -> str:
    """An ``<img src=...>`` with a local PNG/JPEG replaced by its data URI (a missing file: the alt text)."""
    src = html.unescape(match.group(2))
    path = (base / src) if not Path(src).is_absolute() else Path(src)
    if not path.is_file() or path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        return f"<em>[figure missing: {html.escape(src)}]</em>"
    mime = "image/png" if path.suffix.lower() == ".png" else "image/jpeg"
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'{match.group(1)}data:{mime};base64,{data}{match.group(3)}'


def markdown_to_html(text: str, base: Path, title: str) -> str:
    """``text`` (Markdown with pipe tables) as a standalone page; images (paths relative to ``base``) embedded.

    Links to other pages stay links; nothing is fetched when the page is opened (no scripts, fonts or remote
    images)."""
    body = markdown.markdown(text, extensions=["tables"], output_format="html")
    body = re.sub(r'(<img[^>]*\bsrc=")([^"]+)("[^>]*>)', lambda m: _embed(m, base), body)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head>\n<body>\n{body}\n</body></html>\n")
