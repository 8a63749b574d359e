"""Sub-commands of `cellctl`; each module registers its own parser."""

from cellctl.commands import (
    acquire_cmd,
    config_cmd,
    demo_cmd,
    design_cmd,
    heat_plan_cmd,
    hmi_cmd,
    inspect_cmd,
    opcua_cmd,
    plan_cmd,
    report_cmd,
    router_cmd,
    run_cmd,
    scan_cmd,
    sim_cmd,
    synth_cmd,
    worker_cmd,
)

# The order `cellctl --help` lists them in: the cell, then offline tools, then maintenance.
COMMAND_MODULES = [
    demo_cmd,
    sim_cmd,
    run_cmd,
    worker_cmd,
    router_cmd,
    scan_cmd,  # scan, status, watch
    hmi_cmd,  # hmi, history
    opcua_cmd,  # opcua
    plan_cmd,
    inspect_cmd,
    design_cmd,
    synth_cmd,
    report_cmd,
    heat_plan_cmd,
    acquire_cmd,  # reassemble, calibrate
    config_cmd,
]
