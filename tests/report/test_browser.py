"""report.html in a real browser: headless Chromium over its DevTools protocol, opened from disk."""

from __future__ import annotations

import asyncio
import base64
import io
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from tests.report.cdp import chromium_page
from tests.report.conftest import PLATE_ID

# Everything the page's plots and their labels are, read back from the live DOM.
_PLOTS_JS = """
(() => {
  const out = [];
  for (const fig of document.querySelectorAll('figure.plot')) {
    const svg = fig.querySelector('svg');
    const r = fig.getBoundingClientRect();
    out.push({
      plot: fig.dataset.plot, line: fig.dataset.line || null,
      x: r.left + window.scrollX, y: r.top + window.scrollY, w: r.width, h: r.height,
      svg: !!svg, paths: svg ? svg.querySelectorAll('path').length : 0,
      images: svg ? svg.querySelectorAll('image').length : 0,
      texts: svg ? Array.from(svg.querySelectorAll('text')).map(t => t.textContent) : [],
    });
  }
  return {
    plots: out,
    scripts: document.querySelectorAll('script').length,
    h1: document.querySelector('header h1').textContent,
    boldInHeader: document.querySelectorAll('header b').length,
    verdictClass: document.querySelector('header').className,
    tableRows: Array.from(document.querySelectorAll('table.lines tbody tr')).map(
      tr => [tr.dataset.line, tr.className]),
    reworkRows: document.querySelectorAll('table.rework tbody tr').length,
    height: document.documentElement.scrollHeight,
  };
})()
"""


def _decode_png(b64: str) -> np.ndarray:
    return imread(io.BytesIO(base64.b64decode(b64)), format="png")[..., :3]


async def _inspect(html: Path, work: Path) -> dict:
    async with chromium_page(work) as page:
        for domain in ("Runtime", "Log", "Network", "Page"):
            await page.send(f"{domain}.enable")
        await page.send(
            "Emulation.setDeviceMetricsOverride",
            {"width": 1400, "height": 1000, "deviceScaleFactor": 1, "mobile": False},
        )
        await page.send("Page.navigate", {"url": html.as_uri()})
        await page.wait_for("Page.loadEventFired")
        # line plots off the screen are laid out only when scrolled to (content-visibility: auto): this
        # test crops every plot from one capture of the whole page, so it has them all laid out now
        # (tests/hmi/test_result_pages_large.py checks they are drawn when scrolled to)
        await page.evaluate(
            "document.head.insertAdjacentHTML('beforeend',"
            " '<style>.plots figure.plot{content-visibility:visible}</style>')"
        )
        dom = await page.evaluate(_PLOTS_JS)
        crops = []
        for p in dom["plots"]:
            shot = await page.send(
                "Page.captureScreenshot",
                {
                    "format": "png",
                    "captureBeyondViewport": True,
                    "clip": {"x": p["x"], "y": p["y"], "width": p["w"], "height": p["h"], "scale": 1},
                },
            )
            crops.append(_decode_png(shot["data"]))
        full = await page.send("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True})
        (work / "report_screenshot.png").write_bytes(base64.b64decode(full["data"]))
        await asyncio.sleep(0.2)  # late console messages
        return {"dom": dom, "crops": crops, "events": list(page.events)}


@pytest.mark.slow
def test_report_page_renders_every_plot_without_errors_or_network_requests(reported, tmp_path: Path) -> None:
    truth, written = reported
    html = next(p for p in written if p.suffix == ".html")
    got = asyncio.run(_inspect(html, tmp_path))
    dom, events = got["dom"], got["events"]

    errors = [
        e
        for e in events
        if (
            e["method"] == "Runtime.consoleAPICalled"
            and e["params"]["type"] in ("error", "assert", "warning")
        )
        or e["method"] == "Runtime.exceptionThrown"
        or (e["method"] == "Log.entryAdded" and e["params"]["entry"]["level"] in ("error", "warning"))
    ]
    assert errors == []
    urls = [e["params"]["request"]["url"] for e in events if e["method"] == "Network.requestWillBeSent"]
    assert html.as_uri() in urls
    assert [u for u in urls if u != html.as_uri() and not u.startswith("data:")] == []
    assert dom["scripts"] == 0

    # header: verdict and the plate id as text (escaped, not markup)
    assert dom["verdictClass"] == truth.report.verdict
    assert PLATE_ID in dom["h1"] and dom["boldInHeader"] == 0

    names = [ln.name for ln in truth.report.lines]
    kinds = [p["plot"] for p in dom["plots"]]
    assert kinds.count("top-view") == 1 and kinds.count("coverage") == 1
    assert [p["line"] for p in dom["plots"] if p["plot"] == "line"] == names
    for p, crop in zip(dom["plots"], got["crops"], strict=True):
        assert p["svg"] and p["w"] > 300 and p["h"] > 150, p
        # rendered, not blank: a good share of non-white pixels and real contrast
        ink = np.mean(crop.min(axis=2) < 0.9)
        assert ink > 0.03 and crop.std() > 0.05, (p["plot"], p["line"], ink, crop.std())
        if p["plot"] == "line":
            assert any(t.startswith(p["line"]) for t in p["texts"]), p["texts"]
            assert any(t.startswith("Zmax") for t in p["texts"])
    top = next(p for p, c in zip(dom["plots"], got["crops"], strict=True) if p["plot"] == "top-view")
    top_crop = got["crops"][kinds.index("top-view")]
    # every detection line labelled on the map, the reference corner marked, the colour map drawn
    assert set(names) <= set(top["texts"])
    assert "REF (0, 0)" in top["texts"]
    assert top["images"] >= 1
    saturated = np.mean(top_crop.max(axis=2) - top_crop.min(axis=2) > 0.25)
    assert saturated > 0.02, saturated
    # the unscanned patch is drawn in red on the coverage plot: its area in pixels, within a margin
    cov_crop = got["crops"][kinds.index("coverage")]
    cov = dom["plots"][kinds.index("coverage")]
    red = (cov_crop[..., 0] > 0.6) & (cov_crop[..., 1] < 0.35) & (cov_crop[..., 2] < 0.35)
    x0, y0, x1, y1 = truth.hole_box_mm
    assert 0 < red.sum() < 4 * (x1 - x0 + 10) * (y1 - y0 + 10) * (cov["w"] / 1200.0) ** 2, red.sum()

    # the tables: one row per line, pass/fail class as judged
    assert dom["tableRows"] == [[ln.name, "pass" if ln.passed else "fail"] for ln in truth.report.lines]
    assert dom["reworkRows"] >= 2  # the dent and the bump
    shot = tmp_path / "report_screenshot.png"
    assert shot.stat().st_size > 50_000
    assert imread(shot).shape[0] >= dom["height"] - 2
