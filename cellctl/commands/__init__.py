"""Sub-commands of `cellctl`; each module registers its own parser."""

from cellctl.commands import (
    acquire_cmd,
    config_cmd,
    demo_cmd,
    inspect_cmd,
    plan_cmd,
    report_cmd,
    run_cmd,
    scan_cmd,
    sim_cmd,
    synth_cmd,
    worker_cmd,
)

COMMAND_MODULES = [
    config_cmd,
    acquire_cmd,
    synth_cmd,
    inspect_cmd,
    worker_cmd,
    report_cmd,
    plan_cmd,
    run_cmd,
    sim_cmd,
    scan_cmd,
    demo_cmd,
]
