"""Servo travel time of an optimised pose order against raster order.

A few hundred poses of an anisotropic plan on the default four-servo rig; every move's
duration comes from the servos' trapezoid velocity/acceleration profiles
(``Kinematics.move_time``), starting from the park pose.  Prints one JSON object:
the ordered travel time, the raster-order travel time measured in the same run, and their
ratio (target: at least 2).
"""

from __future__ import annotations

import json
import time

from gonio.capture.plan import plan_from_dict
from gonio.capture.schedule import build_schedule
from gonio.rig.config import default_rig_config
from gonio.rig.kinematics import Kinematics

PLAN = {
    "name": "benchmark: anisotropic grid",
    "grid": {
        "theta_i_deg": {"start": 0, "stop": 60, "step": 15},
        "phi_i_deg": {"start": 0, "stop": 270, "step": 90},
        "theta_o_deg": {"start": 10, "stop": 70, "step": 15},
        "phi_o_deg": {"start": 0, "stop": 300, "step": 60},
    },
    "reductions": {"reciprocity": True},
    "exclusions": {"grazing_limit_deg": 80},
}


def main() -> None:
    cfg = default_rig_config()
    kin = Kinematics(cfg)
    t0 = time.perf_counter()
    sched = build_schedule(plan_from_dict(PLAN), kin, cfg.park_rad)
    wall = time.perf_counter() - t0
    n = sum(1 for s in sched.steps if s["kind"] == "sample")
    print(
        json.dumps(
            {
                "benchmark": "plan_order",
                "poses": n,
                "figure": "total servo travel time, optimised order (s)",
                "ordered_travel_s": round(sched.travel_time_s, 2),
                "baseline": "raster (grid) order (s)",
                "raster_travel_s": round(sched.raster_travel_time_s, 2),
                "ratio": round(sched.raster_travel_time_s / sched.travel_time_s, 2),
                "planning_wall_s": round(wall, 2),
            }
        )
    )


if __name__ == "__main__":
    main()
