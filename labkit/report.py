"""Reports as Markdown and self-contained HTML from one list of blocks.

A :class:`Report` collects headings, paragraphs, tables and images (paths relative to the
report's folder); :meth:`Report.write` renders both ``NAME.md`` and ``NAME.html``
atomically. Inline markup in text is limited to ``**bold**`` and ```code```, which both
renderers understand.
"""

from __future__ import annotations

import html
import re
from dataclasses import dataclass, field
from pathlib import Path

from labkit.io.atomic import write_text_atomic

_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 72rem; margin: 2rem auto; padding: 0 1rem;
       color: #222; line-height: 1.45; }
table { border-collapse: collapse; margin: 1rem 0; font-size: 0.9rem; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.6rem; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f3f3f3; }
figure { display: inline-block; margin: 0.5rem; vertical-align: top; text-align: center; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.85rem; color: #555; }
code { background: #f3f3f3; padding: 0 0.2rem; }
"""


@dataclass
class Report:
    """A document of blocks rendered to Markdown and HTML."""

    title: str
    blocks: list[tuple] = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> None:
        """A section heading (level 2–4)."""
        self.blocks.append(("heading", text, level))

    def paragraph(self, text: str) -> None:
        """A paragraph of text."""
        self.blocks.append(("paragraph", text))

    def bullets(self, items: list[str]) -> None:
        """A bulleted list."""
        self.blocks.append(("bullets", list(items)))

    def table(self, header: list[str], rows: list[list[str]]) -> None:
        """A table of strings (first column left-aligned, the rest right-aligned)."""
        self.blocks.append(("table", list(header), [list(map(str, row)) for row in rows]))

    def figures(self, items: list[tuple[str, str]], *, width_px: int | None = None) -> None:
        """Images side by side: (path relative to the report, caption) each."""
        self.blocks.append(("figures", list(items), width_px))

    def images(self) -> list[str]:
        """Every image path the report refers to."""
        return [path for block in self.blocks if block[0] == "figures" for path, _ in block[1]]

    def markdown(self) -> str:
        """The report as Markdown."""
        lines = [f"# {self.title}", ""]
        for kind, *content in self.blocks:
            if kind == "heading":
                text, level = content
                lines += ["#" * level + " " + text, ""]
            elif kind == "paragraph":
                lines += [content[0], ""]
            elif kind == "bullets":
                lines += [f"- {item}" for item in content[0]] + [""]
            elif kind == "table":
                header, rows = content
                lines.append("| " + " | ".join(header) + " |")
                lines.append("|---" + "|---:" * (len(header) - 1) + "|")
                lines += ["| " + " | ".join(row) + " |" for row in rows] + [""]
            elif kind == "figures":
                lines += [f"![{caption}]({path})" for path, caption in content[0]] + [""]
        return "\n".join(lines)

    def html(self) -> str:
        """The report as one HTML page (images linked relatively)."""
        parts = [
            "<!DOCTYPE html>",
            '<html lang="en"><head><meta charset="utf-8">',
            f"<title>{html.escape(self.title)}</title><style>{_STYLE}</style></head><body>",
            f"<h1>{html.escape(self.title)}</h1>",
        ]
        for kind, *content in self.blocks:
            if kind == "heading":
                text, level = content
                parts.append(f"<h{level}>{_inline(text)}</h{level}>")
            elif kind == "paragraph":
                parts.append(f"<p>{_inline(content[0])}</p>")
            elif kind == "bullets":
                items = "".join(f"<li>{_inline(item)}</li>" for item in content[0])
                parts.append(f"<ul>{items}</ul>")
            elif kind == "table":
                header, rows = content
                head = "".join(f"<th>{_inline(h)}</th>" for h in header)
                body = "".join(
                    "<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in row) + "</tr>"
                    for row in rows
                )
                parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            elif kind == "figures":
                items, width = content
                style = f' style="width:{width}px"' if width else ""
                for path, caption in items:
                    parts.append(
                        f'<figure{style}><a href="{html.escape(path)}"><img src="'
                        f'{html.escape(path)}" alt="{html.escape(caption)}"></a>'
                        f"<figcaption>{_inline(caption)}</figcaption></figure>"
                    )
        parts.append("</body></html>")
        return "\n".join(parts) + "\n"

    def write(self, folder: str | Path, name: str = "report") -> tuple[Path, Path]:
        """Write ``NAME.md`` and ``NAME.html`` into `folder` atomically; (md, html) paths."""
        folder = Path(folder)
        md, page = folder / f"{name}.md", folder / f"{name}.html"
        write_text_atomic(md, self.markdown())
        write_text_atomic(page, self.html())
        return md, page


def file_stem(name: str) -> str:
    """A file-name-safe stem of a method or figure name (ASCII letters, digits, ``_``)."""
    stem = "".join(c if c.isascii() and c.isalnum() else "_" for c in name).strip("_")
    while "__" in stem:
        stem = stem.replace("__", "_")
    return stem


def _inline(text: str) -> str:
    escaped = html.escape(text)
    escaped = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", escaped)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", escaped)
