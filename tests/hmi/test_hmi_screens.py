"""The HMI's pages in a real browser against a status the test publishes (no cell).

Playwright drives Debian's Chromium (as test_hmi_browser.py does) against an HMI server in this
process with a fake link (tests/support/hmi_server.py): the test publishes the `CellStatus` the
daemon would, queues the replies of triggers and controls, and reads what the page sent. Covers
issue 44's flow on screen: the Scan page's motion counters, abort asked once, a second start of a
plate already in the cell asked first, the Cell page's state, job and queue consistent with
verdicts and no server paths, every control on a 1280 x 800 screen with touch targets of 48 px,
and the Start form not offered to a viewer.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from playwright import sync_api as playwright_sync

from analysis.contracts.results import LineSeries, ResultsArrays
from cellctl.api import ControlReply, TriggerAccepted
from tests.support.hmi_server import USERS, LocalHmi
from tests.support.reports import report_json
from tests.support.waits import wait_until_sync

pytestmark = [pytest.mark.process, pytest.mark.timeout(180)]  # Chromium is a process of its own

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]  # fmt: skip
DONE_JOB, FAILED_JOB = "20261201T100000-aaaa0001", "20261201T110000-aaaa0002"
ABORTED_JOB = "20261201T120000-aaaa0003"
MOTION = {"cycles": 48211, "egm_stale_cycles": 3, "egm_lost_cycles": 1, "egm_reply_p50_us": 180.0,
          "egm_reply_p99_us": 412.0, "egm_reply_max_us": 905.0, "max_tracking_error_mm": 0.437,
          "max_tracking_t_traj_s": 36.054}  # fmt: skip


def _job_dir(
    data: Path,
    job_id: str,
    plate: str,
    verdict: str | None,
    state: str = "done",
    n_lines: int = 1,
    t: str = "10",
    failing_line: bool = False,
) -> None:
    d = data / "jobs" / job_id
    d.mkdir(parents=True)
    rec = {"job_id": job_id, "plate_id": plate, "design": "p.ply", "design_path": "/srv/cell/designs/p.ply",
           "placement": None, "state": state, "created_utc": f"2026-12-01T{t}:00:00Z",
           "history": [{"state": state, "t_utc": "2026-12-01T10:00:00Z", "message": f"{state} by olga"}], "info": {}}  # fmt: skip
    (d / "job.json").write_text(json.dumps(rec))
    if verdict is None:
        return
    zmax = 1.0 if verdict == "pass" else 4.0
    # transverse lines across the 400 x 300 mm plate at x = 100, 130, ...: from y = 0 to y = 300
    lines = [{"family": "transverse", "index": k + 1, "name": f"T{k + 1}", "zmax_mm": zmax + 0.1 * k,
              "sz_avg_mm": 0.5, "pass": verdict == "pass" and not (failing_line and k == 0),
              "start_plate_mm": [100.0 + 30 * k, 0.0], "end_plate_mm": [100.0 + 30 * k, 300.0]}
             for k in range(n_lines)]  # fmt: skip
    tolerances = {
        "standard": "test",
        "deviation_standard_mm": 1.0,
        "deviation_limit_mm": 2.0,
        "judge_at": "limit",
    }
    report = report_json(lines, verdict, plate_id=plate, tolerances=tolerances, plate_size_mm=[400.0, 300.0])
    (d / "report.json").write_text(report)


def status(state: str = "idle", job: dict | None = None, queue: list | None = None, recent: list | None = None,
           message: str = "") -> dict:  # fmt: skip
    return {"cell_id": "cell-1", "state": state, "t_utc": "2026-12-07T10:00:00.000Z", "job": job,
            "queued": len(queue or []), "queue": queue or [], "recent": recent or [], "workers": ["w1"],
            "message": message}  # fmt: skip


def job(state: str, plate: str = "P-7", job_id: str = "20261207T100000-bbbb0001", **kw) -> dict:
    return {"job_id": job_id, "plate_id": plate, "state": state, "stage": kw.pop("stage", state), **kw}


@pytest.fixture(scope="module")
def hmi(tmp_path_factory) -> Iterator[LocalHmi]:
    root = tmp_path_factory.mktemp("hmi-screens")
    _job_dir(root / "data", DONE_JOB, "P-1", "pass", failing_line=True)
    _job_dir(root / "data", FAILED_JOB, "P-2", "fail")
    _job_dir(root / "data", ABORTED_JOB, "P-3", None, state="aborted")
    for k, verdict in enumerate(("fail", "pass")):  # a plate of 11 lines, two rounds
        _job_dir(root / "data", f"20261202T1{k}0000-rrrr000{k}", "P-R", verdict, n_lines=11, t=f"1{k}")
    # the deviation map and one line's profile of the done job
    res = root / "data" / "jobs" / DONE_JOB / "results"
    res.mkdir()
    s_mm = np.linspace(0.0, 300.0, 120)
    xy = np.stack(np.meshgrid(np.linspace(0, 400, 40), np.linspace(0, 300, 30)), -1).reshape(-1, 2)
    dev_mm = 2.6 * np.sin(s_mm / 60.0)
    ResultsArrays(xy, np.sin(xy[:, 0] / 80.0), np.array([400.0, 300.0]),
                  [LineSeries(s_mm, np.zeros_like(s_mm), -dev_mm, dev_mm)], np.zeros((0, 2))).save(res / "results.npz")  # fmt: skip
    (res / "report.csv").write_text("line,zmax\nT1,1.0\n")
    (root / "designs").mkdir()
    (root / "designs" / "p.ply").write_text("not a mesh")  # listed; its preview says it cannot be read
    with LocalHmi(root) as h:
        yield h


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    return Path(os.environ.get("HMI_SCREENSHOTS") or tmp_path_factory.mktemp("hmi-screens-shots"))


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    with playwright_sync.sync_playwright() as pw:
        b = pw.chromium.launch_persistent_context(
            str(tmp_path_factory.mktemp("chromium-profile")),
            executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS, viewport={"width": 1280, "height": 800},
            bypass_csp=True, has_touch=True,
        )  # fmt: skip
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def page(browser, hmi):
    browser.clear_cookies()
    hmi.link.sent.clear()
    hmi.link.replies.clear()
    p = browser.new_page()
    errors: list[str] = []
    p.on("pageerror", lambda e: errors.append(str(e)))
    p.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    try:
        yield p
    finally:
        p.close()
    expected = ("401", "403", "404", "422", "429", "503")  # refusals the cases provoke (no map, no reply)
    assert not [e for e in errors if not any(c in e for c in expected)], errors


def login(page, hmi: LocalHmi, user: str, hash_: str = "#cell") -> None:
    page.goto(hmi.url + "/" + hash_)
    page.fill("#login-user", user)
    page.fill("#login-password", USERS[user][1])
    page.click("#login-submit")
    page.wait_for_selector("#app:not(.hidden)")
    page.wait_for_function("document.querySelector('#conn').classList.contains('up')")


def publish(page, hmi: LocalHmi, st: dict) -> None:
    """Publish ``st`` and wait until the page has it."""
    st = dict(st, t_utc=f"2026-12-07T10:00:{publish.n % 60:02d}.{publish.n // 60 % 1000:03d}Z")
    publish.n += 1
    hmi.publish(st)
    page.wait_for_function(f"document.body.dataset.statusT === '{st['t_utc']}'", timeout=10_000)


publish.n = 0  # type: ignore[attr-defined]


def test_the_scan_page_shows_the_motion_counters_when_the_cell_publishes_them(page, hmi, shots) -> None:
    login(page, hmi, "olga", "#scan")
    publish(page, hmi, status("scanning", job("scanning", stage="pass (2/6)", fraction=0.4, profiles=900)))
    assert page.is_hidden("#scan-motion")  # no counters published: no line
    publish(
        page,
        hmi,
        status("scanning", job("scanning", stage="pass (2/6)", fraction=0.4, profiles=900, motion=MOTION)),
    )
    page.wait_for_selector("#scan-motion:not(.hidden)")
    text = page.text_content("#scan-motion")
    assert "3 stale cycles" in text and "1 lost cycle ·" in text, text
    assert "reply p99 412 µs" in text and "max tracking error 0.44 mm at 36.1 s" in text, text
    box = page.locator("#scan-motion").bounding_box()
    assert box and box["y"] + box["height"] <= 800  # on screen with the progress
    page.screenshot(path=str(shots / "hmi-scan-motion.png"))
    # counters without a reply histogram yet: a dash, not "null"
    publish(
        page,
        hmi,
        status("scanning", job("scanning", fraction=0.5, motion=dict(MOTION, egm_reply_p99_us=None))),
    )
    assert "reply p99 -" in page.text_content("#scan-motion")
    publish(page, hmi, status("idle", None))
    assert page.is_hidden("#scan-motion")


def test_abort_asks_once_and_sends_one_abort_for_the_job_on_screen(page, hmi) -> None:
    login(page, hmi, "olga", "#scan")
    j = job("scanning", stage="pass (1/4)", fraction=0.2)
    publish(page, hmi, status("scanning", j))
    page.click("#btn-abort")
    page.wait_for_selector("#confirm:not(.hidden)")
    assert "P-7" in page.text_content("#confirm-text")
    page.click("#confirm-no")  # changed their mind: nothing sent
    page.wait_for_selector("#confirm.hidden", state="attached")
    assert hmi.link.sent == []
    hmi.link.replies.append(
        ControlReply(action="abort", job_id=j["job_id"], state="idle", job_state="aborted")
    )
    page.click("#btn-abort")
    page.click("#confirm-yes")
    page.wait_for_function(
        "document.getElementById('scan-notice').textContent.includes('aborted')"
    )  # the reply
    assert page.is_hidden("#confirm")
    assert [(a, json.loads(b)) for a, b in hmi.link.sent] == [
        ("abort", {"job_id": j["job_id"], "requested_by": "olga"})
    ]
    assert page.text_content("#scan-error") == ""
    # pause asks nothing
    hmi.link.replies.append(
        ControlReply(action="pause", job_id=j["job_id"], state="paused", job_state="paused")
    )
    page.click("#btn-pause")
    wait_until_sync(lambda: not hmi.link.replies, 2.0, "the pause answered")  # it reached the cell
    assert [a for a, _ in hmi.link.sent] == ["abort", "pause"]
    assert page.is_hidden("#confirm")


def test_a_second_start_of_a_plate_in_the_cell_asks_first_and_the_form_forgets_the_plate(page, hmi) -> None:
    login(page, hmi, "olga", "#start")
    page.wait_for_selector("#start-design option", state="attached")
    publish(page, hmi, status("scanning", job("scanning", plate="P-7", fraction=0.3),
                              queue=[{"job_id": "20261207T100500-cccc0001", "plate_id": "P-8", "position": 1}]))  # fmt: skip
    for k, v in (("#start-x", "1500"), ("#start-y", "0"), ("#start-z", "300"), ("#start-yaw", "0")):
        page.fill(k, v)
    for plate, words in (("P-7", "scanning"), ("P-8", "queued (position 1")):
        page.fill("#start-plate", plate)
        page.click("#start-submit")
        page.wait_for_selector("#confirm:not(.hidden)")
        assert words in page.text_content("#confirm-text"), page.text_content("#confirm-text")
        page.click("#confirm-no")
        assert page.text_content("#start-error") == "Not started."
    assert hmi.link.sent == []
    hmi.link.replies.append(
        TriggerAccepted(job_id="20261207T101000-dddd0001", state="queued", queue_position=2)
    )
    page.fill("#start-plate", "P-7")
    page.click("#start-submit")
    page.click("#confirm-yes")
    page.wait_for_function("location.hash === '#scan'")
    assert [(a, json.loads(b)["plate_id"]) for a, b in hmi.link.sent] == [("trigger", "P-7")]
    # a plate not in the cell starts without a question; the form forgot the last plate
    page.goto(hmi.url + "/#start")
    page.wait_for_selector("#start-design option", state="attached")
    assert page.input_value("#start-plate") == ""
    hmi.link.replies.append(
        TriggerAccepted(job_id="20261207T101100-dddd0002", state="queued", queue_position=3)
    )
    page.fill("#start-plate", "P-9")
    page.click("#start-submit")
    page.wait_for_function("location.hash === '#scan'")
    assert page.is_hidden("#confirm")
    assert [json.loads(b)["plate_id"] for _, b in hmi.link.sent] == ["P-7", "P-9"]


def test_the_cell_page_keeps_state_job_and_queue_consistent_with_verdicts_and_no_paths(
    page, hmi, tmp_path
) -> None:
    login(page, hmi, "vic")
    recent = [
        job(
            "done",
            plate="P-1",
            job_id=DONE_JOB,
            message="report written to /srv/cell/data/jobs/x/results/report.json",
        ),
        job("done", plate="P-2", job_id=FAILED_JOB, message="done (pass 3/8)"),
    ]
    publish(page, hmi, status("idle", recent[1], recent=recent))
    assert page.text_content("#cell-state") == "idle"
    assert page.text_content("#cell-job-label") == "Last job"
    text = page.text_content("#cell-job")
    assert "done done" not in text and "P-2" in text
    page.wait_for_function("document.getElementById('cell-job').textContent.includes('FAIL')")
    assert page.text_content("#cell-queue").strip() == "empty"
    assert page.locator("#cell-queue ol, #cell-queue li").count() == 0  # no "1. empty"
    rows = page.locator("#cell-recent tr[data-job]")
    assert rows.count() == 2
    table = page.text_content("#cell-recent")
    assert "/srv/" not in table and "report.json" in table and "(pass 3/8)" in table
    assert page.text_content(f"#cell-recent tr[data-job='{DONE_JOB}'] td:nth-child(4)") == "PASS"
    assert page.text_content(f"#cell-recent tr[data-job='{FAILED_JOB}'] td:nth-child(4)") == "FAIL"
    # a job in progress and two waiting
    queue = [
        {"job_id": f"20261207T1005{k}0-eeee000{k}", "plate_id": f"P-{k + 3}", "position": k} for k in (1, 2)
    ]
    publish(
        page,
        hmi,
        status("scanning", job("scanning", stage="pass (1/4)", fraction=0.25), queue=queue, recent=recent),
    )
    assert page.text_content("#cell-job-label") == "Job in progress"
    assert "scanning: pass (1/4)" in page.text_content("#cell-job")
    lines = [t.strip() for t in page.locator("#cell-queue > div").all_text_contents()]
    assert lines[0].startswith("1. P-4") and lines[1].startswith("2. P-5"), lines
    page.screenshot(path=str(tmp_path / "hmi-cell-queue.png"))


def _small_or_off_screen(page) -> list[str]:
    """Visible controls smaller than 48 x 48 px or outside the 1280 x 800 screen (a checkbox counts
    with its label, which takes the touch)."""
    return page.evaluate(
        """() => {
          const bad = [];
          for (const el of document.querySelectorAll('button, a, input, select, label.check')) {
            const r = el.getBoundingClientRect();
            if (!r.width || !r.height || getComputedStyle(el).visibility === 'hidden') continue;
            if (el.closest('.hidden') || el.closest('label.check') && el.tagName === 'INPUT') continue;
            const name = el.id || el.textContent.trim().slice(0, 30) || el.tagName;
            if (r.height < 48 || r.width < 48) bad.push(`${name}: ${r.width.toFixed(0)} x ${r.height.toFixed(0)}`);
            if (el.closest('header, .actions, #page-start, #login') && (r.bottom > 800 || r.right > 1280))
              bad.push(`${name}: off screen at ${r.left.toFixed(0)}, ${r.top.toFixed(0)}`);
          }
          return bad;
        }"""
    )


def test_every_control_is_on_screen_at_1280_by_800_with_touch_targets_of_48_px(page, hmi, tmp_path) -> None:
    login(page, hmi, "erin", "#scan")
    long = "the sensor reports a window of 312 mm at a stand-off of 180 mm; " * 4
    publish(page, hmi, status("scanning", job("scanning", stage="pass (3/6)", fraction=0.6, message=long, motion=MOTION),
                              message=long))  # fmt: skip
    for btn in ("#btn-pause", "#btn-resume", "#btn-abort"):
        box = page.locator(btn).bounding_box()
        assert box and box["y"] + box["height"] <= 800, (btn, box)
    page.screenshot(path=str(tmp_path / "hmi-scan-1280.png"))
    bad = {"scan": _small_or_off_screen(page)}
    shown = {
        "#cell": "#cell-recent tr",
        "#start": "#start-design option",
        "#history/P-1": "#history-jobs a",
        f"#result/{DONE_JOB}": "#result-downloads a",
    }
    for hash_, selector in shown.items():
        page.goto(hmi.url + "/" + hash_)
        page.wait_for_selector(selector, state="attached")
        bad[hash_] = _small_or_off_screen(page)
    page.goto(hmi.url + "/#history/P-1")
    page.wait_for_selector("#history-jobs a")
    bad["history links"] = _small_or_off_screen(page)
    assert not any(bad.values()), bad
    # the locate choice: the box beside its words, the placement greyed out when the cell finds the plate
    page.goto(hmi.url + "/#start")
    page.check("#start-locate")
    assert page.is_disabled("#start-x")
    opacity = page.evaluate("getComputedStyle(document.getElementById('start-x')).opacity")
    assert float(opacity) < 0.5
    cb, label = page.locator("#start-locate").bounding_box(), page.locator("label.check").bounding_box()
    assert cb and label and cb["x"] - label["x"] < 20


def test_a_viewer_is_not_offered_the_start_form_even_by_its_url(page, hmi) -> None:
    login(page, hmi, "vic", "#start")
    page.wait_for_function("document.body.dataset.page === 'cell'")
    assert page.is_hidden("#page-start") and page.is_hidden("#nav-start")
    assert page.evaluate("location.hash") == "#cell"
    publish(page, hmi, status("scanning", job("scanning", fraction=0.1)))
    page.goto(hmi.url + "/#scan")
    assert page.is_hidden("#btn-abort") and page.is_hidden("#btn-pause")


def _points(n: int, z: float = 0.0) -> list[list[float]]:
    return [[float(k), float(k % 7), z] for k in range(n)]


def _shown_points(page) -> int:
    return int(page.get_attribute("#scan-points", "data-points") or 0)


def test_the_live_cloud_survives_a_reload_and_a_new_job_starts_empty(page, hmi) -> None:
    a, b = "20261207T110000-ffff0001", "20261207T111000-ffff0002"
    hmi.link.live[a] = (_points(500), 9)
    login(page, hmi, "olga", "#scan")
    publish(page, hmi, status("scanning", job("scanning", job_id=a, fraction=0.4)))
    page.wait_for_function("Number(document.getElementById('scan-points').dataset.points) === 500")
    # a chunk the cloud above already holds is not added twice; the next one is
    hmi.event({"type": "live", "job_id": a, "seq": 10, "profiles": 1, "xyz_mm": _points(32)})
    page.wait_for_function("Number(document.getElementById('scan-points').dataset.points) === 532")
    hmi.link.live[a] = (_points(532), 10)
    page.reload()  # the operator reloads mid-scan: the whole cloud so far comes back
    page.wait_for_selector("#app:not(.hidden)")
    page.wait_for_function("Number(document.getElementById('scan-points').dataset.points) === 532")
    # the next job: its view starts empty, not with the previous plate's cloud
    publish(page, hmi, status("planning", job("planning", job_id=b, plate="P-8")))
    page.wait_for_function("Number(document.getElementById('scan-points').dataset.points) === 0")
    hmi.event({"type": "live", "job_id": b, "seq": 0, "profiles": 1, "xyz_mm": _points(32, 5.0)})
    page.wait_for_function("Number(document.getElementById('scan-points').dataset.points) === 32")


def test_a_watched_job_leads_to_its_result_and_an_aborted_one_says_so(page, hmi) -> None:
    login(page, hmi, "olga", "#scan")  # the page was opened, not the scan started from it
    running = job("scanning", job_id=DONE_JOB, plate="P-1", fraction=0.9)
    publish(page, hmi, status("scanning", running))
    done = job("done", job_id=DONE_JOB, plate="P-1", message="done")
    publish(page, hmi, status("idle", done, recent=[done]))
    hmi.event({"type": "history", "job_id": DONE_JOB})
    page.wait_for_function(f"location.hash === '#result/{DONE_JOB}'")
    page.wait_for_selector("#result-verdict.pass")
    assert page.text_content("#result-title") == f"Plate P-1 · job {DONE_JOB}"  # as written, not upper-cased
    # an abort with a job queued: the page moves on to the next job and says the first was aborted
    page.goto(hmi.url + "/#scan")
    a = job("scanning", job_id="20261207T120000-abab0001", plate="P-10", fraction=0.3)
    nxt = job("planning", job_id="20261207T120100-abab0002", plate="P-11")
    publish(
        page, hmi, status("scanning", a, queue=[{"job_id": nxt["job_id"], "plate_id": "P-11", "position": 1}])
    )
    aborted = dict(a, state="aborted", message="aborted by olga")
    publish(page, hmi, status("planning", nxt, recent=[aborted]))
    page.wait_for_function("document.getElementById('scan-notice').textContent.includes('aborted')")
    assert "P-10" in page.text_content("#scan-notice") and "P-11" in page.text_content("#scan-job")
    assert page.evaluate("location.hash") == "#scan"


def test_an_aborted_jobs_result_says_why_without_empty_views(page, hmi) -> None:
    login(page, hmi, "vic", f"#result/{ABORTED_JOB}")
    page.wait_for_function("document.getElementById('result-verdict').textContent === 'ABORTED'")
    for tile in ("#result-views", "#result-lines-tile", "#result-rework-tile", "#result-plots-tile"):
        assert page.is_hidden(tile), tile
    assert "aborted by olga" in page.text_content("#result-meta")


def test_plots_have_ticks_on_both_axes_titles_clear_of_the_data_and_distinct_line_colours(
    page, hmi, tmp_path
) -> None:
    login(page, hmi, "vic", f"#result/{DONE_JOB}")
    page.wait_for_function("document.querySelectorAll('#result-plots canvas[data-yticks]').length === 1")
    plot = page.locator("#result-plots canvas").first
    assert int(plot.get_attribute("data-yticks")) >= 3 and int(plot.get_attribute("data-xticks")) >= 3
    # the title's line (baseline at 19 px) is above the plot area: the limit lines cannot cross it
    assert int(plot.get_attribute("data-plot-top")) >= 24
    page.goto(hmi.url + "/#history/P-R")
    page.wait_for_function("document.getElementById('history-rounds').dataset.rounds === '2'")
    page.wait_for_function("document.getElementById('history-convergence').dataset.series")
    series = json.loads(page.get_attribute("#history-convergence", "data-series"))
    assert [n for n, _, _ in series] == [f"T{k}" for k in range(1, 12)]
    assert len({colour for _, colour, _ in series}) == 11  # 11 lines, 11 colours: none repeats
    assert (
        int(page.get_attribute("#history-convergence", "data-xticks")) == 2
    )  # rounds 1 and 2, whole numbers
    page.locator("#history-rounds").screenshot(path=str(tmp_path / "hmi-history-convergence.png"))


def test_a_log_out_in_one_tab_closes_the_other_tabs_socket_and_shows_its_log_in(page, browser, hmi) -> None:
    login(page, hmi, "olga", "#scan")
    other = browser.new_page()  # the same browser: the same session cookie
    try:
        other.goto(hmi.url + "/#cell")
        other.wait_for_function("document.querySelector('#conn').classList.contains('up')")
        page.click("#logout")
        other.wait_for_selector("#login:not(.hidden)", timeout=5_000)
        assert not other.evaluate("document.querySelector('#conn').classList.contains('up')")
        assert not hmi.server.sockets
    finally:
        other.close()


def test_the_top_view_shows_the_plate_frame_the_lines_and_the_numbered_rework_regions(
    page, hmi, tmp_path
) -> None:
    login(page, hmi, "vic", f"#result/{DONE_JOB}")
    page.wait_for_function("document.getElementById('result-top').dataset.regions")
    top = page.locator("#result-top")
    assert top.get_attribute("data-lines") == "T1"
    # line 0's deviation 2.6 sin(s / 60) passes the 2 mm limit twice: above it near s = 94, below near s = 283
    assert top.get_attribute("data-regions") == "2"
    items = page.locator("#result-rework li").all_text_contents()
    assert len(items) == 2, items
    assert (
        items[0].startswith("1 line T1: from (100, ") and "below the design here: it must come up" in items[0]
    )
    assert (
        items[1].startswith("2 line T1: from (100, ")
        and "above the design here: it must come down" in items[1]
    )
    page.locator("#result-views").screenshot(path=str(tmp_path / "hmi-result-top.png"))
