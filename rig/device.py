"""The rig device: move the light and camera to directions, verify, stop safely.

:class:`Rig` implements :class:`gonio.devices.RigDevice` (``read``, ``move_to``, ``stop``,
``park``, ``torque_off``).  It is given a bus (any :class:`gonio.rig.bus.BusTransport`:
the dynamixel-sdk :class:`~gonio.rig.transport.Transport` by default, the simulator's
in-process loopback in tests) and has one :class:`Servo` per joint.  A move is
one SYNC_WRITE of goal positions followed by cyclic SYNC_READs of each servo's state
block until every servo is in position within tolerance or the timeout passes (the loop
waits on an abort event between reads; the state, not the clock, ends it).  On a
hardware error (register 70, read in the same block) every servo's torque is cut and a
:class:`RigFault` names the servo and the error bits.  Torque goes off on every exit
path: ``close()``, the context manager, any exception during a move, :meth:`Rig.stop`,
SIGINT and SIGTERM.

Errors are typed (:mod:`gonio.errors`): :class:`PoseRefused` with a
:class:`RefusalReason` before anything moved, :class:`BusError` from the bus when a servo
does not answer, :class:`RigFault` (``servo``, ``error_bits``) for hardware errors, move
timeouts and stops.
"""

from __future__ import annotations

import itertools
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.devices import MoveResult, RigState
from gonio.errors import BusError, PoseRefused, RefusalReason, RigError, RigFault
from gonio.radiometry.frames import angle_between
from gonio.rig import control_table as ct
from gonio.rig.bus import BusTransport
from gonio.rig.config import JOINT_NAMES, RigConfig
from gonio.rig.kinematics import (
    Kinematics,
    approach_of_move,
    pre_move_side,
    side_after,
    take_up_servo,
)
from gonio.rig.servo import Servo, ServoState
from gonio.rig.transport import Transport

__all__ = ["MoveResult", "Rig", "RigStatus"]

log = logging.getLogger("gonio.rig")

#: How far (rad) the directions of a ``joints=`` hint may lie from the request: far below
#: one pulse (1.5e-3 rad), far above the rounding of joints written to JSON and read back.
_HINT_TOLERANCE_RAD = 1e-6

#: How far past its goal (joint angle, rad) a pre-move takes a joint whose backlash the
#: move itself would not take up (its side unknown, or a reversal shorter than the play),
#: so that it approaches the goal from a known side.
PRE_MOVE_RAD = math.radians(1.0)


@dataclass
class RigStatus:
    """Snapshot of every servo (see :class:`ServoState`) plus bus counters."""

    servos: list[ServoState]
    counters: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "servos": [
                {
                    "id": s.dxl_id,
                    "joint": s.joint,
                    "position_deg": math.degrees(s.position),
                    "goal_deg": math.degrees(s.goal),
                    "velocity_deg_s": math.degrees(s.velocity),
                    "current_a": s.current,
                    "voltage_v": s.voltage,
                    "temperature_c": s.temperature,
                    "torque": s.torque,
                    "moving": s.moving,
                    "hardware_error": s.hardware_error,
                    "hardware_error_names": s.error_names,
                }
                for s in self.servos
            ],
            "counters": dict(self.counters),
        }


class Rig:
    """The gonioreflectometer: servos, kinematics and safe motion.

    Parameters
    ----------
    config
        Rig configuration (bus, servos, geometry, motion).
    transport
        The bus (a :class:`~gonio.rig.bus.BusTransport`, not yet opened); None builds the
        dynamixel-sdk :class:`~gonio.rig.transport.Transport` from ``config.bus``.
    port, baud_rate
        Override ``config.bus.port`` / ``config.bus.baud_rate`` of the transport built
        here (not allowed together with ``transport``).
    clock
        What :attr:`MoveResult.duration <gonio.devices.MoveResult.duration>` is timed on,
        s (a virtual bus's servo clock behind a pty); default the transport's ``clock()``
        when it has one (the loopback), else the wall clock.

    Examples
    --------
    >>> with Rig(load_rig_config("rig.toml")) as rig:          # doctest: +SKIP
    ...     result = rig.move_to(wi, wo)
    """

    def __init__(
        self,
        config: RigConfig,
        *,
        transport: BusTransport | None = None,
        port: str | None = None,
        baud_rate: int | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.config = config
        if transport is None:
            bus = config.bus
            transport = Transport(
                port or bus.port,
                baud_rate or bus.baud_rate,
                retries=bus.retries,
                timeout_ms=bus.timeout_ms,
                latency_timer_ms=bus.latency_timer_ms,
            )
        elif port is not None or baud_rate is not None:
            raise RigError("Rig: give either a transport or port/baud_rate, not both")
        self.transport: BusTransport = transport
        # a virtual bus's servo clock times moves in servo time; a real one has none
        self._clock: Callable[[], float] = clock or getattr(transport, "clock", time.monotonic)
        self.kinematics = Kinematics(config)
        self.servos = {s.joint: Servo(self.transport, s) for s in config.servos}
        self._ids = tuple(s.id for s in config.servos)
        self._by_id = {s.id: s for s in self.servos.values()}
        self._abort = threading.Event()
        self._saved_handlers: dict[int, Any] = {}
        self._opened = False
        # Sign of each joint's last commanded move (0 unknown), for this connection only.
        self._approach: dict[str, int] = dict.fromkeys(JOINT_NAMES, 0)
        #: Joints the last move pre-moved to take their backlash up (for tests, logs).
        self.last_pre_move: dict[str, int] = {}
        #: Keep torque on when the ``with`` block ends normally (never after an error).
        self.hold_on_exit = False

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> Rig:
        """Open the port, check every configured servo and configure it.

        Torque is left as found unless a servo must be reconfigured (EEPROM) or rebooted;
        a servo holding a pose from ``gonio rig move --hold`` keeps holding it.

        Raises
        ------
        BusError
            Unknown port (``cause="port"``), no answer at all (wrong baud rate?) or from
            some IDs (``cause="timeout"``, ``servo`` when one).
        RigError
            Model mismatch.
        """
        self.transport.open()
        self._forget_approach()
        try:
            self._check_servos()
            for s in self.servos.values():
                bits = s.read("hardware_error_status")
                if bits:
                    log.warning(
                        "servo %d reports hardware error 0x%02X from before; rebooting it",
                        s.id,
                        bits,
                    )
                    self.transport.reboot(s.id)
                s.configure()
        except BaseException:
            self.transport.close()
            raise
        self._opened = True
        return self

    def _check_servos(self) -> None:
        found = {}
        for i in self._ids:
            found[i] = self.transport.ping(i, retries=min(self.config.bus.retries, 1))
        missing = [i for i, v in found.items() if v is None]
        port, baud = self.transport.port_name, self.transport.baud_rate
        if len(missing) == len(self._ids):
            raise BusError(
                f"no servo answered on {port} at {baud} baud (IDs {list(self._ids)}): check the "
                "baud rate (bus.baud_rate must match the servos' Baud Rate register), power "
                "and cabling",
                cause="timeout",
            )
        if missing:
            names = ", ".join(f"{i} ({self._by_id[i].joint})" for i in missing)
            raise BusError(
                f"servo(s) {names} did not answer on {port}; "
                f"found {sorted(set(found) - set(missing))}",
                servo=missing[0] if len(missing) == 1 else None,
                cause="timeout",
            )
        for i, (number, fw) in found.items():
            s = self._by_id[i]
            model = ct.MODELS_BY_NUMBER.get(number)
            if model is None or model.name != s.config.model:
                got = model.name if model else "an unknown model"
                raise RigError(
                    f"servo {i} ({s.joint}) is {got} (model number {number}, firmware {fw}) "
                    "but the "
                    f"configuration says {s.config.model} (model number {s.model.number})"
                )

    def close(self) -> None:
        """Cut torque on every servo and close the port (idempotent)."""
        if self.transport.is_open:
            try:
                self.torque_off()
            finally:
                self.transport.close()
        self._opened = False

    def __enter__(self) -> Rig:
        self.open()
        self._install_signal_handlers()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None and self.hold_on_exit:
                log.info("leaving torque on (hold_on_exit)")
                self.transport.close()
            else:
                self.close()
        finally:
            self._restore_signal_handlers()

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            self._abort.set()
            raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

        for sig in (signal.SIGINT, signal.SIGTERM):
            self._saved_handlers[sig] = signal.signal(sig, handler)

    def _restore_signal_handlers(self) -> None:
        for sig, h in self._saved_handlers.items():
            signal.signal(sig, h)
        self._saved_handlers.clear()

    def torque_off(self) -> list[int]:
        """Cut torque on every servo: one broadcast WRITE, then each servo verified.

        Signals are held off meanwhile so a second Ctrl-C cannot interrupt it.

        Returns
        -------
        list of int
            IDs of the servos whose torque off could not be confirmed (empty when every
            servo confirmed it), so callers never report a safe state they did not see.
        """
        main = threading.current_thread() is threading.main_thread()
        old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            self.transport.reset()
            reg = ct.MODELS[self.config.servos[0].model]["torque_enable"]
            self.transport.broadcast_write(reg, 0)
            failed: list[int] = []
            for s in self.servos.values():
                try:
                    s.torque(False)
                except RigError as exc:
                    failed.append(s.id)
                    log.error("could not confirm torque off on servo %d: %s", s.id, exc)
            if not failed:
                log.info("torque off on servos %s", list(self._ids))
            return failed
        finally:
            self._forget_approach()  # without torque a joint may settle on either side
            if main:
                signal.signal(signal.SIGINT, old)

    def _forget_approach(self) -> None:
        self._approach = dict.fromkeys(JOINT_NAMES, 0)

    @property
    def approach(self) -> dict[str, int]:
        """Sign of each joint's last commanded move in joint angle (+1 up, -1 down, 0
        unknown: nothing moved it since the connection was opened or torque went off)."""
        return dict(self._approach)

    def stop(self) -> None:
        """Stop the move in progress at once; safe from another thread or a signal handler.

        Only sets an event (no bus traffic here): the moving thread sees it within one
        poll, cuts torque on every servo and raises :class:`RigFault`.
        """
        self._abort.set()

    # ------------------------------------------------------------------ state
    def read(self) -> RigState:
        """Joints (rad), temperatures (degC), error bits and motion of every servo.

        One SYNC_READ of the state block.

        Raises
        ------
        BusError
            A servo did not answer.
        """
        st = self.read_states()
        return RigState(
            joints={j: float(st[j].position) for j in JOINT_NAMES},
            temperatures={j: float(st[j].temperature) for j in JOINT_NAMES},
            errors={j: int(st[j].hardware_error) for j in JOINT_NAMES},
            moving=any(s.moving for s in st.values()),
            approach=dict(self._approach),
        )

    def read_states(self) -> dict[str, ServoState]:
        """Every servo's state block in one SYNC_READ, by joint name."""
        blocks = self.transport.sync_read(self._ids, ct.STATE_BLOCK_START, ct.STATE_BLOCK_LEN)
        return {self._by_id[i].joint: self._by_id[i].decode_state(b) for i, b in blocks.items()}

    def status(self) -> RigStatus:
        """Positions, temperatures, voltages, currents, torque and errors of every servo."""
        st = self.read_states()
        return RigStatus([st[j] for j in JOINT_NAMES if j in st], dict(self.transport.counters))

    def joints(self) -> dict[str, float]:
        """Read-back joint angles (rad)."""
        return {j: s.position for j, s in self.read_states().items()}

    def directions(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Present (wi, wo) in the sample frame from the read-back joints."""
        return self.kinematics.forward(self.joints())

    # ------------------------------------------------------------------ motion
    def _check_target(
        self, target: Mapping[str, float], current: Mapping[str, float]
    ) -> dict[int, int]:
        missing = [j for j in JOINT_NAMES if j not in target]
        if missing:
            raise RigError(f"target pose lacks joint(s) {missing}")
        goals = {self.servos[j].id: self.servos[j].to_pulses(float(target[j])) for j in JOINT_NAMES}
        self._refuse_if(
            self.kinematics.joints_refusal(target) or self.kinematics.path_refusal(current, target)
        )
        return goals

    @staticmethod
    def _refuse_if(refusal: PoseRefused | None) -> None:
        if refusal is not None:
            raise PoseRefused(refusal.reason, f"refusing to move: {refusal}")

    def move_joints(
        self, target: Mapping[str, float], timeout: float | None = None
    ) -> dict[str, float]:
        """Move to joint angles (rad) and wait until every servo is in position.

        Everything is checked (limits, camera shadow, arm clearance, path) before anything
        moves.  Returns the read-back joint angles (rad).

        Raises
        ------
        PoseRefused
            Target not allowed (nothing moved).
        BusError
            A servo did not answer.
        RigFault
            Hardware error, timeout or :meth:`stop` during the move (torque is off on
            every servo).
        """
        states = self.read_states()
        current = {j: st.position for j, st in states.items()}
        goals = self._check_target(target, current)
        return self._move_pulses(goals, timeout, states)

    def _move_pulses(
        self,
        goals: dict[int, int],
        timeout: float | None,
        states: Mapping[str, ServoState] | None = None,
    ) -> dict[str, float]:
        """Move to ``goals`` (servo ID -> pulses): the backlash pre-move when needed, the
        move, and the approach signs it leaves."""
        states = self.read_states() if states is None else states
        self.last_pre_move = {}
        pre = self._pre_move_goals(goals, states)
        if pre is not None:
            pre_goals, self.last_pre_move = pre
            log.info("taking up the backlash of %s first", sorted(self.last_pre_move))
            self._move_raw(pre_goals, timeout, states)
            self._track_approach(pre_goals, states)
            states = self.read_states()
        achieved = self._move_raw(goals, timeout, states)
        self._track_approach(goals, states)
        return achieved

    def _track_approach(self, goals: Mapping[int, int], states: Mapping[str, ServoState]) -> None:
        # The sign of the commanded change in joint angle.  A goal within the position
        # tolerance of where the servo stands does not move it (a servo's deadband: it
        # lands within a pulse of its goal and stays there), so it keeps the sign: else
        # re-sending a pose's goal to a servo that landed a pulse short flips the recorded
        # side while the gears stay where they are.
        tol = self.config.motion.position_tolerance_pulses
        for st in states.values():
            d = goals[st.dxl_id] - st.position_pulses
            if abs(d) > tol:
                direction = self._by_id[st.dxl_id].config.direction
                self._approach[st.joint] = direction * (1 if d > 0 else -1)

    def _pre_move_goals(
        self, goals: Mapping[int, int], states: Mapping[str, ServoState]
    ) -> tuple[dict[int, int], dict[str, int]] | None:
        """Goals of the pre-move that takes up the backlash before a move that would not:
        of each joint with backlash whose side is unknown and whose move is shorter than
        its take-up (:func:`gonio.rig.kinematics.take_up_pulses`), and of each joint whose
        move reverses its side by less than that (the gears would stop inside their play:
        a real servo's 2-pulse reversal against a 3.5-pulse backlash).  Each goes
        :data:`PRE_MOVE_RAD` past its goal on the side it will approach from (its present
        side, below when unknown; the other when that is not allowed), the others stay.
        None when no joint needs it."""
        tol = self.config.motion.position_tolerance_pulses
        need: list[tuple[ServoState, int]] = []
        for st in states.values():
            first = int(
                pre_move_side(
                    take_up_servo(self._by_id[st.dxl_id].config, self.config),
                    goals[st.dxl_id] - st.position_pulses,
                    self._approach[st.joint],
                    tol,
                )
            )
            if first:
                need.append((st, first))
        if not need:
            return None
        current = {j: st.position for j, st in states.items()}
        target = {
            st.joint: self._by_id[st.dxl_id].to_joint(goals[st.dxl_id]) for st in states.values()
        }
        pre_goals = {st.dxl_id: st.position_pulses for st in states.values()}
        sides = {}
        kin = self.kinematics
        for st, first in need:
            servo = self._by_id[st.dxl_id]
            for side in (first, -first):
                q = dict(current)
                q[st.joint] = target[st.joint] - side * PRE_MOVE_RAD
                lo, hi = servo.config.limits_rad
                if lo <= q[st.joint] <= hi and not (
                    kin.joints_refusal(q)
                    or kin.path_refusal(current, q)
                    or kin.path_refusal(q, target)
                ):
                    pre_goals[st.dxl_id] = int(round(servo.config.pulses(q[st.joint])))
                    sides[st.joint] = side
                    break
            else:
                log.warning("%s: no room to take up its backlash; side unknown", st.joint)
        return (pre_goals, sides) if sides else None

    def _move_raw(
        self,
        goals: dict[int, int],
        timeout: float | None,
        states: Mapping[str, ServoState] | None = None,
    ) -> dict[str, float]:
        motion = self.config.motion
        timeout = motion.move_timeout_s if timeout is None else timeout
        tol = motion.position_tolerance_pulses
        self._abort.clear()
        try:
            states = self.read_states() if states is None else states
            self._raise_on_fault(states)
            goal_reg = ct.MODELS[self.config.servos[0].model]["goal_position"]
            off = [s for s in states.values() if not s.torque]
            if off:  # hold where they are, then enable: no jump
                self.transport.sync_write(goal_reg, {s.dxl_id: s.position_pulses for s in off})
                for s in off:
                    self._by_id[s.dxl_id].torque(True)
            self.transport.sync_write(goal_reg, goals)
            deadline = time.monotonic() + timeout
            while True:
                states = self.read_states()
                self._raise_on_fault(states)
                lost = {
                    s.dxl_id: goals[s.dxl_id]
                    for s in states.values()
                    if s.goal_pulses != goals[s.dxl_id]
                }
                if lost:  # a SYNC_WRITE has no reply: a lost one shows up here
                    self.transport.counters["goal_resends"] += 1
                    log.warning("goal not taken by servo(s) %s; sending it again", sorted(lost))
                    self.transport.sync_write(goal_reg, lost)
                elif all(
                    not s.moving and abs(s.position_pulses - goals[s.dxl_id]) <= tol
                    for s in states.values()
                ):
                    return {j: s.position for j, s in states.items()}
                late = [s for s in states.values() if self._late(s, goals, tol)]
                if time.monotonic() > deadline:
                    raise RigFault(
                        f"move timed out after {timeout:.1f} s: servo(s) "
                        + "; ".join(
                            f"{s.dxl_id} ({s.joint}) at {s.position_pulses}, goal {goals[s.dxl_id]}"
                            for s in late
                        ),
                        servo=late[0].dxl_id if len(late) == 1 else None,
                    )
                # Wait for the next state poll; stop() or a signal wakes it at once.
                if self._abort.wait(motion.poll_interval_s):
                    raise RigFault(
                        "move stopped on request before servo(s) "
                        f"{[s.dxl_id for s in late]} reached their goals; torque cut on all "
                        "servos",
                        servo=late[0].dxl_id if len(late) == 1 else None,
                    )
        except BaseException:
            log.error("move aborted; cutting torque on every servo")
            self.torque_off()
            raise

    @staticmethod
    def _late(s: ServoState, goals: Mapping[int, int], tol: int) -> bool:
        return abs(s.position_pulses - goals[s.dxl_id]) > tol or s.moving

    def _raise_on_fault(self, states: Mapping[str, ServoState]) -> None:
        for s in states.values():
            if s.hardware_error or s.dxl_id in self.transport.alerts:
                bits = s.hardware_error or self._by_id[s.dxl_id].read("hardware_error_status")
                names = ", ".join(s.error_names) or "alert bit without a register 70 code"
                raise RigFault(
                    f"servo {s.dxl_id} ({s.joint}) hardware error 0x{bits:02X} ({names}); "
                    "torque cut "
                    f"on all servos; power-cycle or `gonio rig home` after fixing the cause "
                    f"(a REBOOT clears the error)",
                    servo=s.dxl_id,
                    error_bits=bits,
                )

    def quantised_goals(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        joints: Mapping[str, float],
        present: Mapping[str, int] | None = None,
    ) -> dict[int, int]:
        """Goal pulses near ``joints`` whose directions are closest to (wi, wo).

        Each joint can round down or up; of the 16 combinations the one with the smallest
        worst direction error wins (plain rounding can add the half-pulse errors of three
        joints along one direction).  On an as-built rig each combination is judged with
        the approach signs its move from ``present`` (joint -> pulses) would leave.

        Raises
        ------
        PoseRefused
            ``RefusalReason.PULSE_RANGE`` when the rounded goal of a joint at its limit
            falls outside the servo's configured range.
        """
        options = []
        for j in JOINT_NAMES:
            s = self.servos[j]
            p = s.config.pulses(float(joints[j]))
            lo, hi = math.floor(p), math.ceil(p)
            options.append(sorted({lo, hi}))
        combos = np.array(list(itertools.product(*options)), dtype=np.float64)
        q = {
            j: np.array([self.servos[j].to_joint(c) for c in combos[:, k]])
            for k, j in enumerate(JOINT_NAMES)
        }
        appr = None
        if not self.kinematics.nominal and present is not None:
            appr = {}
            for k, j in enumerate(JOINT_NAMES):
                d = combos[:, k] - present[j]
                keep = self._approach[j] or 1  # unknown: the pre-move comes from below
                # within the deadband the servo does not move, and a short reversal is
                # approached from the present side (_pre_move_goals): both keep it
                appr[j] = side_after(
                    take_up_servo(self.servos[j].config, self.config),
                    d,
                    keep,
                    self.config.motion.position_tolerance_pulses,
                )
        ai, ao = self.kinematics.forward(q, appr)
        err = np.maximum(angle_between(ai, np.asarray(wi)), angle_between(ao, np.asarray(wo)))
        best = combos[int(np.argmin(err))]
        goals = {}
        for k, j in enumerate(JOINT_NAMES):
            s = self.servos[j]
            try:
                s.to_pulses(s.to_joint(best[k]))  # limit check of the rounded value
            except PoseRefused:
                raise PoseRefused(
                    RefusalReason.PULSE_RANGE,
                    f"{j} (servo {s.id}): goal {int(best[k])} pulses, rounded from "
                    f"{s.config.pulses(float(joints[j])):.3f}, lies past the servo's limits "
                    f"[{s.config.min_deg}, {s.config.max_deg}] deg",
                ) from None
            goals[s.id] = int(best[k])
        return goals

    def move_to(
        self,
        wi: ArrayLike,
        wo: ArrayLike,
        *,
        joints: Mapping[str, float] | None = None,
        timeout: float | None = None,
    ) -> MoveResult:
        """Put the light along ``wi`` and the camera along ``wo`` (sample frame).

        Without ``joints``, solves the inverse kinematics from the present pose (least
        motion among the reachable, collision-free solutions).  With ``joints`` (joint
        name -> rad, the solution a dry run chose), moves there instead, after checking
        that they do put the devices along (wi, wo) and checking them again (holder rim,
        limits, shadowing, arm clearance, the path from the present pose).  The goal is
        quantised to pulses, sent in one SYNC_WRITE; the rig waits until every servo is
        in position, reads back and returns the achieved directions.

        Parameters
        ----------
        wi, wo
            Directions towards the light and the camera, shape (3,) (need not be unit).
        joints
            Optional joint angles (rad) for this pose, as a dry run chose them.
        timeout
            Seconds before the move counts as failed (default ``motion.move_timeout_s``).

        Raises
        ------
        PoseRefused
            Unreachable request (nothing moved); ``reason`` says which rule.
        BusError
            A servo did not answer.
        RigFault
            Hardware error, timeout or :meth:`stop` during the move; torque is off on
            every servo.
        RigError
            ``joints`` lacks a joint or does not put the devices along (wi, wo).
        """
        t0 = self._clock()
        wi = np.asarray(wi, dtype=np.float64)
        wo = np.asarray(wo, dtype=np.float64)
        states = self.read_states()
        current = {j: st.position for j, st in states.items()}
        if joints is None:
            q = self.kinematics.inverse(wi, wo, current=current, approach=self._approach)
        else:
            q = self._hinted(wi, wo, joints, current)
        wi_u, wo_u = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
        present = {j: st.position_pulses for j, st in states.items()}
        goals = self.quantised_goals(wi_u, wo_u, q, present)
        target = {j: self.servos[j].to_joint(goals[self.servos[j].id]) for j in JOINT_NAMES}
        self._check_target(target, current)
        achieved = self._move_pulses(goals, timeout, states)
        ai, ao = self.kinematics.forward(achieved, self._approach)
        return MoveResult(
            wi=wi_u,
            wo=wo_u,
            wi_achieved=ai,
            wo_achieved=ao,
            joints=achieved,
            error_i=float(angle_between(ai, wi_u)),
            error_o=float(angle_between(ao, wo_u)),
            duration=self._clock() - t0,
        )

    def _hinted(
        self,
        wi: NDArray[np.float64],
        wo: NDArray[np.float64],
        joints: Mapping[str, float],
        current: Mapping[str, float],
    ) -> dict[str, float]:
        """The ``joints=`` hint of :meth:`move_to`, checked as a solution of (wi, wo)."""
        refusal = self.kinematics.direction_refusal(wi, wo)
        if refusal is not None:
            raise PoseRefused(
                refusal.reason,
                f"cannot reach wi={np.round(wi, 6).tolist()}, wo={np.round(wo, 6).tolist()}: "
                f"{refusal}",
            )
        q = {j: float(joints[j]) for j in JOINT_NAMES if j in joints}
        self._refuse_if(
            self.kinematics.joints_refusal(q) or self.kinematics.path_refusal(current, q)
        )
        appr = self._implied_approach(current, q)
        hi, ho = self.kinematics.forward(q, appr)
        off = max(
            float(angle_between(hi, wi / np.linalg.norm(wi))),
            float(angle_between(ho, wo / np.linalg.norm(wo))),
        )
        if not off <= _HINT_TOLERANCE_RAD and not self.kinematics.nominal:
            # As built, the hint was planned with approach signs this move may not give
            # (the rig started elsewhere than the dry run): refine it on this move.
            refined = self.kinematics.refine(wi, wo, q, current, self._approach)[0]
            if refined is not None and max(abs(refined[j] - q[j]) for j in q) < 0.05:
                self._refuse_if(
                    self.kinematics.joints_refusal(refined)
                    or self.kinematics.path_refusal(current, refined)
                )
                return refined
        if not off <= _HINT_TOLERANCE_RAD:
            raise RigError(
                f"joints {q} put the devices {math.degrees(off):.4f} deg from the requested "
                f"wi={np.round(wi, 6).tolist()}, wo={np.round(wo, 6).tolist()}: not a "
                "solution of this pose (plan made with another rig configuration?)"
            )
        return q

    def _implied_approach(
        self, current: Mapping[str, float], q: Mapping[str, float]
    ) -> dict[str, int]:
        # The signs the move current -> q leaves (unknown and unmoved: from below).
        appr = approach_of_move(self.config, current, q, self._approach)
        return {j: v or 1 for j, v in appr.items()}

    def home(self, timeout: float | None = None) -> dict[str, float]:
        """Move to the configured home pose; returns the read-back joints (rad)."""
        return self.move_joints(self.config.home_rad, timeout)

    def park(self, timeout: float | None = None) -> dict[str, float]:
        """Move to the park pose (home unless configured), then cut torque."""
        try:
            return self.move_joints(self.config.park_rad, timeout)
        finally:
            self.torque_off()
