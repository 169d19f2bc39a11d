"""``reduction.json["retention"]``: planned and kept region samples by theta band.

A hand-made schedule and hand-made pose measurements, whose counts are worked out here
by hand: poses never measured plan samples too, the band is that of the larger theta,
the headline stops at 80 deg, and the demo prints the same numbers.
"""

from __future__ import annotations

import numpy as np

from gonio.capture.pose_measure import PoseMeasurement, invalid_pose
from gonio.capture.reduce import retention
from gonio.dataset import Flag


def entry(kind, ti, to):
    return {"kind": kind, "theta_i_deg": ti, "theta_o_deg": to}


def measured(pose, n, n_flagged, source):
    z = np.zeros((n, 3))
    flags = np.zeros(n, np.uint32)
    flags[:n_flagged] = Flag.GEOMETRY_MISMATCH
    return PoseMeasurement(
        pose, "sample", z, z, z, z, z, z, z, flags, [[]] * n, (), geometry_source=source
    )


SCHEDULE = [
    entry("reference", 0.0, 40.0),  # pose 0: not a sample pose
    entry("sample", 0.0, 10.0),  # 1: band 0-10 (10 is its upper end)
    entry("sample", 15.0, 10.0),  # 2: band 10-20 by theta_i
    entry("sample", 30.0, 80.0),  # 3: band 70-80
    entry("sample", 80.0, 5.0),  # 4: band 70-80, never measured
    entry("sample", 30.0, 85.0),  # 5: band 80-90, beyond the headline
]


def test_retention_counts_by_band_of_the_larger_theta():
    grid = 2  # 4 regions a pose
    ms = [
        measured(1, 4, 0, "board"),
        measured(2, 4, 1, "board"),
        measured(3, 4, 0, "rig"),
        measured(5, 4, 2, "rig"),
        # a pose whose frames could not be decoded: one INVALID sample
        invalid_pose(4, np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), "no frame", ()),
    ]
    ret = retention({"schedule": SCHEDULE}, ms, grid)
    bands = {tuple(b["theta_deg"]): (b["planned"], b["kept"]) for b in ret["bands"]}
    assert bands[(0.0, 10.0)] == (4, 4)
    assert bands[(10.0, 20.0)] == (4, 3)
    assert bands[(20.0, 30.0)] == (0, 0)  # listed, with nothing planned
    assert bands[(70.0, 80.0)] == (8, 4)  # pose 4 planned its 4 and kept none
    assert bands[(80.0, 90.0)] == (4, 2)  # listed because planned
    assert next(b for b in ret["bands"] if b["theta_deg"] == [20.0, 30.0])["fraction"] is None
    # headline: poses 1-4, up to 80 deg
    assert (ret["planned"], ret["kept"], ret["up_to_deg"]) == (16, 11, 80.0)
    assert ret["fraction"] == round(11 / 16, 6)
    assert ret["geometry_source"] == {"board": 7, "rig": 6}


def test_the_demo_prints_the_retention():
    from rich.console import Console

    from gonio.app.demo import retention_table
    from gonio.app.demo_report import _retention_lines

    ms = [measured(1, 4, 0, "board"), measured(3, 4, 1, "rig")]
    ret = retention({"schedule": SCHEDULE}, ms, 2)
    console = Console(width=120, record=True)
    console.print(retention_table(ret))
    text = console.export_text()
    assert "70-80" in text and "0-80" in text and "43.8%" in text  # 7 of 16
    assert "board 4, rig 3" in text
    md = "\n".join(_retention_lines(ret))
    assert "**43.8%** up to 80 deg (7 of 16)" in md and "| 70-80 | 8 | 3 | 37.5% |" in md
