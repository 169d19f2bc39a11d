"""Full-state sync reads per second of four servos: gonio's controller vs bare dynamixel-sdk.

Both loops read the same block (registers 64..146 of IDs 1-4: torque, hardware error,
goal, moving, current, velocity, position, voltage, temperature) through the same open
port from the same virtual bus (`gonio sim bus`, its own process) in the same run,
alternating in rounds (order swapped every round) so that machine load affects both
alike; medians over the rounds (and the best round of each).
The controller's figure includes decoding into SI units (``Rig.read_states``).
An extra figure, ``loopback_reads_per_s``: the same controller read over the in-process
loopback transport (the same packets, no pty: the protocol and servo logic alone).
Prints one JSON object.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from dynamixel_sdk import COMM_SUCCESS, GroupSyncRead, PacketHandler, PortHandler

from gonio.rig import control_table as ct
from gonio.rig.config import default_rig_config
from gonio.rig.device import Rig
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.virtual_bus import ServoBus

IDS = (1, 2, 3, 4)


def bare_loop(port: PortHandler, n: int) -> float:
    ph = PacketHandler(2.0)
    group = GroupSyncRead(port, ph, ct.STATE_BLOCK_START, ct.STATE_BLOCK_LEN)
    for i in IDS:
        group.addParam(i)
    t0 = time.perf_counter()
    for _ in range(n):
        if group.txRxPacket() != COMM_SUCCESS:
            raise RuntimeError("bare sync read failed")
        for i in IDS:
            group.getData(i, 132, 4)
    return n / (time.perf_counter() - t0)


def controller_loop(rig: Rig, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        rig.read_states()
    return n / (time.perf_counter() - t0)


def loopback_figure(n: int, rounds: int) -> float:
    """Median reads per second of ``Rig.read_states`` over the loopback transport."""
    bus = ServoBus(IDS)
    for i, p in zip(IDS, (1536, 2048, 2048, 0), strict=True):
        bus.servos[i].set_position(p)
    rig = Rig(default_rig_config(), transport=LoopbackTransport(bus)).open()
    try:
        return float(np.median([controller_loop(rig, n) for _ in range(rounds)]))
    finally:
        rig.close()


def main(n: int = 200, rounds: int = 10) -> dict:
    # The virtual bus runs in its own process (as `gonio sim bus`), so it does not share
    # the GIL with the loops being timed.
    exe = Path(sys.executable).parent / "gonio"
    proc = subprocess.Popen(
        [
            str(exe),
            "sim",
            "bus",
            "--servos",
            ",".join(map(str, IDS)),
            "--positions",
            "1536,2048,2048,0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        port = proc.stdout.readline().strip()
        rig = Rig(default_rig_config(), port=port).open()
        bare_port = rig.transport._port  # same open port, same pty: only the software differs
        ours, bare = [], []
        try:
            for r in range(rounds):
                # alternate the order (ABBA...) so that drifts in machine load cancel
                if r % 2:
                    ours.append(controller_loop(rig, n))
                    bare.append(bare_loop(bare_port, n))
                else:
                    bare.append(bare_loop(bare_port, n))
                    ours.append(controller_loop(rig, n))
        finally:
            rig.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    ours_med, bare_med = float(np.median(ours)), float(np.median(bare))
    loop_med = loopback_figure(n, rounds)  # after the pty rounds: they are the comparison
    return {
        "benchmark": "full-state sync reads of 4 servos (64..146), per second",
        "controller_reads_per_s": round(ours_med, 1),
        "baseline_bare_sdk_reads_per_s": round(bare_med, 1),
        "ratio_controller_over_baseline": round(ours_med / bare_med, 3),
        "controller_overhead_percent": round(100 * (bare_med / ours_med - 1), 1),
        # best round of each (timeit's rule: the least disturbed run), less sensitive to load
        "best_controller_reads_per_s": round(max(ours), 1),
        "best_baseline_reads_per_s": round(max(bare), 1),
        "best_overhead_percent": round(100 * (max(bare) / max(ours) - 1), 1),
        "target_overhead_percent": 20,
        "loopback_reads_per_s": round(loop_med, 1),
        "rounds": rounds,
        "reads_per_round": n,
    }


if __name__ == "__main__":
    print(json.dumps(main()))
