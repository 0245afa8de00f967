"""The report's page checked in a real browser: nothing wider than the page, no overlapping
text, every image loaded (headless Chromium; the tests and ``benchmarks/report_layout.py``).

:func:`check_layout` loads ``report.html`` at a window width with :data:`LAYOUT_CHECK` added
and returns what it found: ``width`` (the page's client width, px), ``page`` (its scroll
width), ``wide`` (elements reaching past the right edge; a wide table scrolls inside its
``.table-wrap`` box and is not counted), ``overlaps`` (pairs of text boxes -- headings,
paragraphs, list items, table cells -- that overlap by more than 1 px each way, neither
containing the other) and ``broken`` (images not loaded).
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

#: run in the page after load: what does not fit, what overlaps, what did not load
LAYOUT_CHECK = r"""
window.addEventListener('load', () => setTimeout(() => {
  const W = document.documentElement.clientWidth, out = {width: W, wide: [], overlaps: [],
    broken: [], page: document.documentElement.scrollWidth};
  for (const el of document.body.querySelectorAll('*')) {
    if (el.closest('.table-wrap') && !el.classList.contains('table-wrap')) continue;
    const r = el.getBoundingClientRect();
    if (r.width && r.right > W + 1) out.wide.push(el.tagName + '.' + el.className);
  }
  for (const img of document.images)
    if (!img.complete || img.naturalWidth === 0) out.broken.push(img.alt);
  const boxes = [];
  for (const el of document.body.querySelectorAll('h1,h2,h3,p,li,th,td')) {
    const r = el.getBoundingClientRect();
    if (r.width && r.height) boxes.push([r.top, r.bottom, r.left, r.right, el]);
  }
  boxes.sort((a, b) => a[0] - b[0]);
  for (let i = 0; i < boxes.length; i++)
    for (let j = i + 1; j < boxes.length && boxes[j][0] < boxes[i][1] - 1; j++) {
      const a = boxes[i], b = boxes[j];
      if (a[4].contains(b[4]) || b[4].contains(a[4])) continue;
      const w = Math.min(a[3], b[3]) - Math.max(a[2], b[2]);
      const h = Math.min(a[1], b[1]) - Math.max(a[0], b[0]);
      if (w > 1 && h > 1) out.overlaps.push(a[4].tagName + '/' + b[4].tagName + ': ' +
                                             a[4].textContent.slice(0, 30));
    }
  const pre = document.createElement('pre');
  pre.id = 'layout-check';
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
}, 300));
"""


def chromium() -> str | None:
    """The headless browser to check with (``chromium`` or ``chromium-browser`` on PATH)."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def check_layout(page: str | Path, width: int, exe: str | None = None,
                 timeout_s: float = 120.0) -> dict:
    """What :data:`LAYOUT_CHECK` finds in the report page ``page`` at ``width`` px (module doc);
    :class:`RuntimeError` when no browser is found or the check did not run."""
    exe = exe or chromium()
    if exe is None:
        raise RuntimeError("no chromium on PATH")
    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp) / "report.html"  # beside nothing: the report inlines its images
        probe.write_text(Path(page).read_text().replace(
            "</body>", f"<script>{LAYOUT_CHECK}</script></body>"))
        dom = subprocess.run(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--no-first-run", f"--user-data-dir={Path(tmp) / 'profile'}",
             f"--window-size={width},1200", "--dump-dom", "--virtual-time-budget=4000",
             probe.as_uri()], capture_output=True, text=True, timeout=timeout_s).stdout
    found = re.search(r'<pre id="layout-check">(.*?)</pre>', dom, re.S)
    if not found:
        raise RuntimeError(f"{page}: the layout check did not run in {exe}")
    return json.loads(html.unescape(found.group(1)))
