"""A Markdown and an HTML page that gather the PNGs of a run, one section per frame, each image with its caption."""

from __future__ import annotations

import html
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["PageImage", "Section", "write_page"]


@dataclass(frozen=True)
class PageImage:
    """One image of the page."""

    path: str
    """Path relative to the page's folder, with forward slashes."""
    caption: str
    """What the image shows."""


@dataclass(frozen=True)
class Section:
    """A heading, a line of text under it and its images."""

    heading: str
    text: str = ""
    images: tuple[PageImage, ...] = field(default_factory=tuple)


_STYLE = (
    "body{font-family:sans-serif;max-width:1300px;margin:auto;padding:1em;color:#222}"
    "figure{margin:0 0 1.5em 0}img{max-width:100%;border:1px solid #ddd}figcaption{font-size:90%;color:#555}"
)


def _markdown(title: str, intro: str, sections: list[Section]) -> str:
    lines = [f"# {title}", "", intro, ""]
    for section in sections:
        lines += [f"## {section.heading}", ""] + ([section.text, ""] if section.text else [])
        for image in section.images:
            lines += [f"![{image.caption}]({image.path})", "", f"*{image.caption}*", ""]
    return "\n".join(lines)


def _html(title: str, intro: str, sections: list[Section]) -> str:
    parts = [
        f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>",
        f"<style>{_STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>{html.escape(intro)}</p>",
    ]
    for section in sections:
        parts.append(f"<h2>{html.escape(section.heading)}</h2>")
        if section.text:
            parts.append(f"<p>{html.escape(section.text)}</p>")
        for image in section.images:
            parts.append(f"<figure><img src=\"{html.escape(image.path, quote=True)}\" "
                         f"alt=\"{html.escape(image.caption, quote=True)}\">"
                         f"<figcaption>{html.escape(image.caption)}</figcaption></figure>")  # fmt: skip
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def write_page(folder: str | Path, title: str, intro: str, sections: list[Section]) -> dict[str, Path]:
    """Write ``index.md`` and ``index.html`` into ``folder``; image paths are relative to it.

    Returns:
        ``{"markdown": path, "html": path}``.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": folder / "index.md", "html": folder / "index.html"}
    paths["markdown"].write_text(_markdown(title, intro, sections))
    paths["html"].write_text(_html(title, intro, sections))
    return paths
