"""abb-robot-client's EGM side in its own process (its egm_pb2 and ours both register ``egm.proto`` in
protobuf's default pool, so they cannot share one interpreter).

``python abb_client_egm_guidance.py PORT DELTA_DEG TIMEOUT_S``: binds PORT, prints ``{"ready": true}``,
answers every EgmRobot with its own joints (a sensor holding still) until a packet of a running
session (motors on, RAPID running) arrives, then guides axis 1 to its position + DELTA_DEG and prints
``{"q0": [...], "q": [...]}`` once it is there (or the timeout passed).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
from abb_robot_client.egm import EGM


def main() -> int:
    port, delta_deg, timeout_s = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
    egm = EGM(port=port)
    print(json.dumps({"ready": True}), flush=True)
    deadline = time.monotonic() + timeout_s
    q0 = None
    q = None
    try:
        while time.monotonic() < deadline:
            ok, state = egm.receive_from_robot(0.1)
            if not ok:
                continue
            q = np.array(state.joint_angles)
            if q0 is None:
                egm.send_to_robot(q)
                if state.motors_on and state.rapid_running:
                    q0 = q
                continue
            target = q0 + np.array([delta_deg, 0, 0, 0, 0, 0])
            egm.send_to_robot(target)
            if abs(q[0] - target[0]) < 0.02:
                break
    finally:
        egm.close()
    print(
        json.dumps({"q0": None if q0 is None else q0.tolist(), "q": None if q is None else q.tolist()}),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
