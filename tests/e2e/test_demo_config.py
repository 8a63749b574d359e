"""The demo's derived configuration: a valid cell.toml on fresh loopback ports."""

from __future__ import annotations

from cellctl.commands.demo_cmd import demo_config, to_toml
from cellctl.config import load_config


def test_demo_config_round_trips_through_toml_with_loopback_ports_and_the_small_plate(tmp_path, repo_root):
    base = load_config(repo_root / "cell.toml").model_dump(mode="json")
    cfg = demo_config(base, tmp_path)
    path = tmp_path / "cell.toml"
    path.write_text(to_toml(cfg))
    c = load_config(path)
    assert c.zenoh.listen[0].startswith("tcp/127.0.0.1:") and c.zenoh.listen != base["zenoh"]["listen"]
    assert c.robot.rws_url == f"http://127.0.0.1:{c.sim.rws_port}"
    assert (c.sim.plate.length_mm, c.sim.plate.width_mm) == (600.0, 400.0)
    assert c.cell.data_dir == tmp_path / "data"
    assert c.sim.rws_users == base["sim"]["rws_users"]
    full = load_config_from(tmp_path, demo_config(base, tmp_path, full=True))
    assert (full.sim.plate.length_mm, full.scan.profile_spacing_mm) == (
        1200.0,
        base["scan"]["profile_spacing_mm"],
    )


def load_config_from(d, cfg):
    p = d / "full.toml"
    p.write_text(to_toml(cfg))
    return load_config(p)


def test_wait_html_report_returns_the_recorded_html_path_and_none_when_no_render_is_recorded(tmp_path):
    import json

    from cellctl.commands.demo_cmd import wait_html_report
    from cellctl.jobstore.jobs import JobRecord

    job_id = "20261207T162328-663ece59"
    job = tmp_path / "jobs" / job_id
    job.mkdir(parents=True)

    def record(**info) -> str:  # a whole job.json, as the daemon writes it (one reader reads it)
        return json.dumps(JobRecord(job_id, "P", "d.ply", "/d.ply", None, state="done", info=info).as_json())

    (job / "job.json").write_text(record(report_utc_s=1.0))
    assert wait_html_report(tmp_path, job_id, timeout_s=0.3) is None
    (job / "job.json").write_text(record(html_s=2.0, report_html="/r/report.html"))
    assert wait_html_report(tmp_path, job_id, timeout_s=5.0) == "/r/report.html"
    assert wait_html_report(tmp_path, "20261207T162328-00000000", timeout_s=0.3) is None


def test_wait_heating_plan_waits_for_the_recorded_plan_and_its_render_and_says_why_there_is_none(tmp_path):
    import json

    from analysis.forming.plan_file import HeatingPlanFile, PlanLine, write_heating_plan
    from cellctl.commands.demo_cmd import wait_heating_plan
    from cellctl.jobstore.jobs import JobRecord

    job_id = "20261207T162328-663ece59"
    job = tmp_path / "jobs" / job_id
    job.mkdir(parents=True)

    def record(**info) -> str:
        return json.dumps(JobRecord(job_id, "P", "d.ply", "/d.ply", None, state="done", info=info).as_json())

    (job / "job.json").write_text(record(report_utc_s=1.0, html_s=2.0))
    assert wait_heating_plan(tmp_path, job_id, timeout_s=0.3)[0].startswith("heating plan: none recorded")
    plan_path = write_heating_plan(
        HeatingPlanFile(status="no_plan", reason="every line is within the standard range"), job / "hp.json"
    )
    (job / "job.json").write_text(
        record(html_s=2.0, heating_plan=str(plan_path), heating_plan_status="no_plan")
    )
    got = wait_heating_plan(tmp_path, job_id, timeout_s=5.0)
    assert got[0] == "no heating plan: every line is within the standard range" and str(plan_path) in got[-1]
    line = PlanLine.model_validate({
        "id": "H1", "order": 1, "start_plate_mm": [120.0, 40.0], "end_plate_mm": [120.0, 760.0], "face": "top",
        "heat_input_j_mm": 900.0, "torch_speed_mm_s": 8.0, "bend_deg": 0.5, "shrink_mm": 0.05,
    })  # fmt: skip
    write_heating_plan(HeatingPlanFile(status="plan", lines=[line]), plan_path)
    # a plan: the demo waits for report.html rendered again with it
    (job / "job.json").write_text(record(html_s=2.0, heating_plan=str(plan_path), heating_plan_status="plan"))
    assert wait_heating_plan(tmp_path, job_id, timeout_s=0.5)[0].startswith("heating plan: none recorded")
    (job / "job.json").write_text(
        record(html_s=2.0, html_with_plan_s=3.0, heating_plan=str(plan_path), heating_plan_status="plan")
    )
    assert wait_heating_plan(tmp_path, job_id, timeout_s=5.0)[0] == line.sentence()
