"""The result page's heating plan: the job API serves heating-plan.json with each line's sentence,
the DXF is a download, a plan that cannot be read is said without the server's paths, and the page
draws the lines over the top view, numbered, with the list and the predicted Zmax per line (one HMI
server in this process with the fake link, tests/support/hmi_server.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from analysis.design.plates import FormingError, GaussianBump, plate_spec
from analysis.forming.plan_file import HeatingPlanFile, read_heating_plan
from analysis.forming.rules import PlanSettings
from analysis.heating_plan import write_job_plan
from cellctl.hmi.server import COOKIE
from tests.support.hmi_server import USERS, LocalHmi
from tests.support.results_fixture import CELL_LAYOUT, write_synthetic_results

PLANNED, UNREADABLE, NONE = "20261207T120000-heat0001", "20261207T120000-heat0002", "20261207T120000-heat0003"


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, HeatingPlanFile]:
    """A 600 x 400 cylinder under-bent by 20 % and its plan (four lines at 40 mm elements)."""
    out = tmp_path_factory.mktemp("planned")
    spec = plate_spec("cylinder", length_mm=600.0, width_mm=400.0)
    error = FormingError(bumps=(GaussianBump(0.0, 0.0, 0.0, 50.0),) * 2, bend_fraction=-0.2)
    write_synthetic_results(out, spec=spec, error=error, n_points=6000, layout=CELL_LAYOUT)
    write_job_plan(out, PlanSettings(element_mm=40.0, max_lines_per_round=4))
    return out, read_heating_plan(out)


@pytest.fixture(scope="module")
def hmi(tmp_path_factory: pytest.TempPathFactory, planned) -> Iterator[LocalHmi]:
    results, _ = planned
    h = LocalHmi(tmp_path_factory.mktemp("hmi"))  # jobs are added before it starts (its history then)
    h.add_done_job(PLANNED, results, "P-HEAT")
    unreadable = h.add_done_job(UNREADABLE, results, "P-HEAT")
    (unreadable / "results" / "heating-plan.json").write_text('{"status": "maybe"}')
    none = h.add_done_job(NONE, results, "P-HEAT")
    (none / "results" / "heating-plan.json").unlink()
    (none / "results" / "heating-plan.dxf").unlink()
    with h:
        yield h


def test_the_job_api_serves_the_plan_with_its_sentences_and_the_dxf_as_a_download(hmi, planned) -> None:
    results, plan = planned
    s = hmi.auth.login("vic", USERS["vic"][1])
    assert s is not None

    async def get_all() -> dict[str, Any]:
        out: dict[str, Any] = {}
        async with aiohttp.ClientSession(cookies={COOKIE: s.token}) as http:
            for job in (PLANNED, UNREADABLE, NONE):
                async with http.get(f"{hmi.url}/api/jobs/{job}") as r:
                    out[job] = await r.json()
            async with http.get(f"{hmi.url}/api/jobs/{PLANNED}/files/heating-plan.dxf") as r:
                out["dxf"] = (r.status, await r.read())
        return out

    got = hmi.run(get_all())
    served = got[PLANNED]["heating_plan"]
    assert served["status"] == "plan"
    assert [ln["sentence"] for ln in served["lines"]] == [ln.sentence() for ln in plan.lines]
    assert served["predicted"]["zmax_mm"] == plan.predicted.zmax_mm
    assert {"heating-plan.json", "heating-plan.dxf"} <= set(got[PLANNED]["files"])
    assert got["dxf"] == (200, (results / "heating-plan.dxf").read_bytes())
    bad = got[UNREADABLE]["heating_plan"]
    assert bad["status"] == "no_plan" and "cannot be read" in bad["reason"]
    assert "/" not in bad["reason"]  # no server path on the crew's screen
    assert got[NONE]["heating_plan"] is None and "heating-plan.dxf" not in got[NONE]["files"]


@pytest.mark.process  # Chromium is a process of its own
def test_the_result_page_draws_the_plan_over_the_map_with_one_sentence_a_line(
    page, hmi, planned, tmp_path
) -> None:
    _, plan = planned
    r = page.request.post(hmi.url + "/api/login", data={"user": "vic", "password": USERS["vic"][1]})
    assert r.status == 200
    page.goto(f"{hmi.url}/#result/{PLANNED}")
    page.wait_for_function(
        "document.getElementById('result-top').dataset.heating !== undefined", timeout=60_000
    )
    assert page.locator("#result-top").get_attribute("data-heating") == ",".join(ln.id for ln in plan.lines)
    items = page.locator("#result-heating li").all_inner_texts()
    assert [t.split(" · ")[0] for t in items] == [ln.sentence() for ln in plan.lines]
    assert "predicted after this round: verdict PASS" in page.locator("#result-heating-meta").inner_text()
    head = page.locator("#result-lines tr").first.inner_text()
    assert "Zmax after heating (predicted)" in head
    assert page.locator("#result-heating-tile").is_visible()
    page.locator("#result-views").screenshot(path=str(tmp_path / "hmi-result-heating.png"))
    page.goto(f"{hmi.url}/#result/{NONE}")
    page.wait_for_function(f"document.body.dataset.resultJob === '{NONE}'", timeout=30_000)
    page.wait_for_function("document.getElementById('result-heating-tile').classList.contains('hidden')")
