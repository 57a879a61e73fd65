"""``report.html``: the Markdown report as one self-contained HTML file.

Same content as ``report.md`` (rendered from it, so the two never disagree), with every figure
the Markdown links embedded as a base64 ``data:`` URI: the file opens anywhere and can be sent on
its own. Nothing is fetched at run time or when the file is opened.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

#: Image types embedded, by file suffix.
MEDIA_TYPES = {".png": "image/png", ".svg": "image/svg+xml", ".jpg": "image/jpeg"}

_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 75em; margin: 2em auto; padding: 0 1em;
       line-height: 1.45; color: #1b1b1b; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #c8c8c8; padding: 0.25em 0.6em; text-align: right; }
th { background: #f0f0f0; }
td:first-child, th:first-child { text-align: left; }
code { background: #f4f4f4; padding: 0 0.2em; }
img { max-width: 100%; height: auto; display: block; margin: 0.5em 0 1.5em; }
figcaption, .caption { color: #444; font-size: 0.92em; }
"""

_IMG = re.compile(r'<img src="([^"]+)"')


def _embed(folder: Path, src: str) -> str:
    """``src`` as a data URI when it names an image file of ``folder``, else unchanged."""
    name = html.unescape(src)
    path = folder / name
    media = MEDIA_TYPES.get(path.suffix.lower())
    if media is None or name != Path(name).name or not path.is_file():
        return src
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f"data:{media};base64,{data}"


def html_report(markdown: str, folder: Path, title: str = "Drive gain identification") -> str:
    """The HTML document of a Markdown report whose images are files of ``folder``.

    Parameters
    ----------
    markdown
        The report (``report.md``'s text).
    folder
        Where the images it links are (relative file names); each is embedded.
    title
        The document's title.

    Returns
    -------
    str
        A complete HTML5 document (UTF-8).
    """
    from markdown_it import MarkdownIt

    # html=False: the report's text is escaped, never interpreted as markup
    body = MarkdownIt("commonmark", {"html": False}).enable("table").render(markdown)
    body = _IMG.sub(lambda m: f'<img src="{_embed(folder, m.group(1))}"', body)
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n<style>{_STYLE}</style>\n</head>\n"
        f"<body>\n{body}</body>\n</html>\n"
    )
