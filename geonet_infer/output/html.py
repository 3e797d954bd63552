"""One self-contained HTML page of plots, pictures and tables (``geonet-infer report``; issue 59).

Plots are plotly figures with plotly.js embedded once in the page (no CDN, no network: the page opens
offline and from a file URL); pictures are JPEG data URIs. plotly is the ``[viz]`` extra.
"""

from __future__ import annotations

import base64
import html
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write

INSTALL = "pip install 'geonet-infer[viz]' (plotly)"
MAX_PAGE_BYTES = 6 * 2**20  # plotly.js is 4.6 MiB of it
THUMB_WIDTH = 360
STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 0.9em; } td, th { border: 1px solid #ddd; padding: 3px 8px; }
th { background: #f4f4f4; text-align: left; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.thumbs { display: grid; grid-template-columns: repeat(3, 1fr); gap: 6px; } .thumbs img { width: 100%; }
.note { color: #a33; } figure { margin: 0; } figcaption { font-size: 0.85em; color: #555; }
"""


def require_plotly() -> ModuleType:
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise InputError(None, "geonet-infer report needs plotly, which is not installed", INSTALL) from None
    return go


class Page:
    """Sections of HTML, in order; :meth:`html` puts them in one page with plotly.js embedded once."""

    def __init__(self, title: str):
        self.title = title
        self.parts: list[str] = []
        self.plots = 0

    def heading(self, text: str) -> None:
        self.parts.append(f"<h2>{html.escape(text)}</h2>")

    def text(self, text: str, note: bool = False) -> None:
        cls = ' class="note"' if note else ""
        self.parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def table(self, headers: list[str], rows: list[list]) -> None:
        def cell(v) -> str:
            if isinstance(v, float):
                return f'<td class="num">{v:.2f}</td>'
            return f"<td>{html.escape(str(v))}</td>"

        head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
        body = "".join("<tr>" + "".join(cell(v) for v in row) + "</tr>" for row in rows)
        self.parts.append(f"<table><tr>{head}</tr>{body}</table>")

    def plot(self, figure) -> None:
        """A plotly figure; the first carries plotly.js (inline), the others use it."""
        figure.update_layout(template="plotly_white", margin={"l": 50, "r": 20, "t": 40, "b": 40})
        self.parts.append(
            figure.to_html(full_html=False, include_plotlyjs=self.plots == 0, config={"displaylogo": False})
        )
        self.plots += 1

    def thumbnails(self, captioned: list[tuple[str, np.ndarray | None]]) -> None:
        """Pictures (RGB uint8) in rows of three, each scaled to :data:`THUMB_WIDTH` and JPEG-encoded."""
        cells = []
        for caption, rgb in captioned:
            img = "" if rgb is None else f'<img alt="{html.escape(caption)}" src="{jpeg_data_uri(rgb)}">'
            cells.append(f"<figure>{img}<figcaption>{html.escape(caption)}</figcaption></figure>")
        self.parts.append('<div class="thumbs">' + "".join(cells) + "</div>")

    def html(self) -> str:
        return (
            f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(self.title)}</title>'
            f"<style>{STYLE}</style></head><body><h1>{html.escape(self.title)}</h1>"
            + "\n".join(self.parts)
            + "</body></html>\n"
        )


def jpeg_data_uri(rgb: np.ndarray) -> str:
    h, w = rgb.shape[:2]
    if w > THUMB_WIDTH:
        rgb = cv2.resize(rgb, (THUMB_WIDTH, max(1, round(h * THUMB_WIDTH / w))), interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(
        ".jpg", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 80]
    )
    if not ok:
        return ""
    return "data:image/jpeg;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def write_page(path: Path, page: Page) -> int:
    """Write the page atomically; its size in bytes. A page over :data:`MAX_PAGE_BYTES` is an error."""
    text = page.html()
    size = len(text.encode("utf-8"))
    if size > MAX_PAGE_BYTES:
        raise InputError(path, f"the page would be {size / 2**20:.1f} MiB, over {MAX_PAGE_BYTES / 2**20:.0f} MiB")
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return size
