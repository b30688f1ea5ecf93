"""Self-contained HTML reports: headings, paragraphs, tables, embedded PNG figures, code blocks.

`HtmlReport` collects blocks and renders one HTML document with the images embedded as base64
(the writers also put each PNG beside the report). Every table cell and text is escaped.
"""

from __future__ import annotations

import base64
import html

__all__ = ["HtmlReport", "fmt"]

_STYLE = """
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 3px 8px; text-align: right; }
th { background: #eee; }
td.l, th.l { text-align: left; }
figure { margin: 1em 0; }
figcaption { font-size: 0.85em; color: #444; }
pre { background: #f5f5f5; padding: 0.6em; overflow-x: auto; }
.note { font-size: 0.9em; color: #444; }
"""


def fmt(v, digits: int = 3) -> str:
    """A number as report text: ``digits`` significant digits, ints and strings as they are."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if v != v:
            return "nan"
        return f"{v:.{digits}g}"
    return str(v)


class HtmlReport:
    """An HTML report built block by block.

    Examples
    --------
    >>> r = HtmlReport("demo")
    >>> r.heading("Table V")
    >>> r.table(["", "systematic"], [["simulated", 4.0]])
    >>> "<table" in r.render()
    True
    """

    def __init__(self, title: str):
        self.title = title
        self._parts: list[str] = []
        self.images: dict[str, bytes] = {}

    def heading(self, text: str, level: int = 2) -> None:
        self._parts.append(f"<h{level}>{html.escape(text)}</h{level}>")

    def paragraph(self, text: str, cls: str | None = None) -> None:
        c = f' class="{cls}"' if cls else ""
        self._parts.append(f"<p{c}>{html.escape(text)}</p>")

    def bullets(self, items) -> None:
        li = "".join(f"<li>{html.escape(str(i))}</li>" for i in items)
        self._parts.append(f"<ul>{li}</ul>")

    def code(self, text: str) -> None:
        self._parts.append(f"<pre>{html.escape(text)}</pre>")

    def table(self, header, rows, table_id: str | None = None, digits: int = 3) -> None:
        """A table; the first column is left aligned. Numbers get ``digits`` significant digits."""
        tid = f' id="{html.escape(table_id)}"' if table_id else ""
        head = "".join(
            f'<th class="l">{html.escape(str(h))}</th>'
            if k == 0
            else f"<th>{html.escape(str(h))}</th>"
            for k, h in enumerate(header)
        )
        body = []
        for row in rows:
            cells = "".join(
                f'<td class="l">{html.escape(fmt(v, digits))}</td>'
                if k == 0
                else f"<td>{html.escape(fmt(v, digits))}</td>"
                for k, v in enumerate(row)
            )
            body.append(f"<tr>{cells}</tr>")
        self._parts.append(f"<table{tid}><tr>{head}</tr>{''.join(body)}</table>")

    def figure(self, name: str, png: bytes, caption: str) -> None:
        """Embed a PNG (kept in ``images`` under ``name`` for the side file)."""
        self.images[name] = png
        data = base64.b64encode(png).decode("ascii")
        self._parts.append(
            f'<figure><img alt="{html.escape(name)}" data-file="{html.escape(name)}" '
            f'src="data:image/png;base64,{data}"/>'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>"
        )

    def render(self) -> str:
        body = "\n".join(self._parts)
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{html.escape(self.title)}</title><style>{_STYLE}</style></head>\n"
            f"<body><h1>{html.escape(self.title)}</h1>\n{body}\n</body></html>\n"
        )
