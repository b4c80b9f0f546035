"""ROS-Industrial "simple message" as MotoROS speaks it on its state port (50241).

Frame: int32 length (header + body, not itself), int32 msg_type, comm_type, reply_code, body;
int32 and float32, packed, in the controller's byte order. JOINT_FEEDBACK (15): int32 group,
int32 valid_fields (1 time, 2 position, 4 velocity, 8 acceleration), float32 time,
float32[10] positions, velocities, accelerations (length 144). ROBOT_STATUS (13): seven int32
(length 40). Pure codec: no sockets.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from keo_service.core.rejects import RejectLog

JOINT_FEEDBACK = 15
ROBOT_STATUS = 13
JOINT_FEEDBACK_LENGTH = 144
ROBOT_STATUS_LENGTH = 40
MAX_FRAME_LENGTH = 4096  # no simple message MotoROS sends is longer
COMM_TYPES = (1, 2, 3)  # topic, request, reply
# Other fixed-size simple messages a controller may send, with their length field
# (ROS-Industrial JOINT_POSITION, JOINT_TRAJ_PT, JOINT_TRAJ_PT_FULL; Motoman MOTION_CTRL and
# MOTION_REPLY). Such a frame is skipped whole. Any other (type, length) pair is taken as
# garbage and passed byte by byte, so random bytes cannot swallow the good frames after them.
OTHER_KNOWN_LENGTHS = {10: 56, 11: 64, 14: 148, 2001: 64, 2002: 72}
VALID_POSITION = 2
VALID_VELOCITY = 4
MAX_JOINTS = 10
MAX_ABS_JOINT = 100.0  # rad: anything larger is garbage, not a joint angle


@dataclass(frozen=True)
class JointFeedback:
    group: int
    valid_fields: int
    time: float
    positions: tuple[float, ...]
    velocities: tuple[float, ...] | None


@dataclass(frozen=True)
class RobotStatusFrame:
    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int


def _prefix(byte_order: str) -> str:
    if byte_order not in ("little", "big"):
        raise ValueError(f"byte_order must be 'little' or 'big', got {byte_order!r}")
    return "<" if byte_order == "little" else ">"


def encode_joint_feedback(
    positions: list[float] | tuple[float, ...],
    byte_order: str = "little",
    velocities: list[float] | None = None,
    group: int = 0,
    time: float = 0.0,
) -> bytes:
    pre = _prefix(byte_order)
    pos = list(positions) + [0.0] * (MAX_JOINTS - len(positions))
    vel = list(velocities or []) + [0.0] * (MAX_JOINTS - len(velocities or []))
    valid = VALID_POSITION | (VALID_VELOCITY if velocities is not None else 0)
    body = struct.pack(f"{pre}iif10f10f10f", group, valid, time, *pos, *vel, *([0.0] * 10))
    return struct.pack(f"{pre}iiii", JOINT_FEEDBACK_LENGTH, JOINT_FEEDBACK, 1, 0) + body


def encode_robot_status(
    values: tuple[int, ...] = (1, 0, 0, 0, 0, 2, 1), byte_order: str = "little"
) -> bytes:
    pre = _prefix(byte_order)
    return struct.pack(f"{pre}iiii7i", ROBOT_STATUS_LENGTH, ROBOT_STATUS, 1, 0, *values)


class SimpleMessageDecoder:
    """Feed bytes, get frames. Bad bytes are counted and skipped until a plausible header."""

    def __init__(self, byte_order: str = "little", max_buffer: int = 65536) -> None:
        self._pre = _prefix(byte_order)
        self._other = ">" if self._pre == "<" else "<"
        self._buf = bytearray()
        self._max_buffer = max_buffer
        self._skipped = 0
        self._rejects = RejectLog(keep=16)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self._offset = 0  # bytes of the connection before the buffer's first

    def _reject(self, counter: str, message: str) -> None:
        self._rejects.at = f"byte {self._offset} of the connection"
        self._rejects.reject(counter, message)

    def _consume(self, n: int) -> None:
        del self._buf[:n]
        self._offset += n

    def reset(self) -> None:
        """Connection lost: a partial frame left in the buffer is counted as truncated."""
        if self._buf:
            self._reject("truncated", f"connection ended inside a frame ({len(self._buf)} bytes)")
        self._buf.clear()
        self._skipped = 0
        self._offset = 0

    def feed(self, data: bytes) -> list[JointFeedback | RobotStatusFrame]:
        self._buf += data
        if len(self._buf) > self._max_buffer:
            self._reject("overflow", f"{len(self._buf)} bytes without a frame; buffer cleared")
            self._consume(len(self._buf))
            return []
        out: list[JointFeedback | RobotStatusFrame] = []
        while len(self._buf) >= 16:
            length, msg_type, comm, _reply = struct.unpack_from(f"{self._pre}iiii", self._buf)
            problem = self._header_problem(length, msg_type, comm)
            if problem is not None:
                if self._skipped == 0:  # one report per bad stretch, not one per byte
                    self._reject(*problem)
                self._skipped += 1
                self.counters["skipped_bytes"] += 1
                self._consume(1)  # resynchronise one byte on
                continue
            if len(self._buf) < 4 + length:
                break
            if self._skipped:
                self.messages.append(f"resynchronised after skipping {self._skipped} bytes")
                self._skipped = 0
            frame = bytes(self._buf[4 : 4 + length])
            item = self._parse(msg_type, frame)  # a reject names the frame's first byte
            self._consume(4 + length)
            if item is not None:
                out.append(item)
        return out

    def _header_problem(self, length: int, msg_type: int, comm: int) -> tuple[str, str] | None:
        if length < 12 or length > MAX_FRAME_LENGTH:
            swapped = struct.unpack(f"{self._other}i", struct.pack(f"{self._pre}i", length))[0]
            hint = (
                " (it reads as a valid length in the other byte order: check robot.byte_order)"
                if swapped in (JOINT_FEEDBACK_LENGTH, ROBOT_STATUS_LENGTH)
                else ""
            )
            return (
                "bad_length",
                f"impossible length {length}, expected 12..{MAX_FRAME_LENGTH}{hint}",
            )
        if (msg_type == JOINT_FEEDBACK and length != JOINT_FEEDBACK_LENGTH) or (
            msg_type == ROBOT_STATUS and length != ROBOT_STATUS_LENGTH
        ):
            return "bad_length", f"type {msg_type} with length {length}"
        if comm not in COMM_TYPES:
            return "bad_header", f"comm_type {comm}, expected one of {COMM_TYPES}"
        if msg_type not in (JOINT_FEEDBACK, ROBOT_STATUS) and (
            OTHER_KNOWN_LENGTHS.get(msg_type) != length
        ):
            return (
                "unknown_type",
                f"message type {msg_type} (length {length}) is not a simple message",
            )
        return None

    def _parse(self, msg_type: int, frame: bytes) -> JointFeedback | RobotStatusFrame | None:
        body = frame[12:]
        if msg_type == ROBOT_STATUS:
            return RobotStatusFrame(*struct.unpack(f"{self._pre}7i", body))
        if msg_type != JOINT_FEEDBACK:
            self._reject("unknown_type", f"message type {msg_type} skipped ({len(frame)} bytes)")
            return None
        group, valid = struct.unpack_from(f"{self._pre}ii", body)
        values = struct.unpack_from(f"{self._pre}f10f10f10f", body, 8)
        time, pos, vel = values[0], values[1:11], values[11:21]
        if not valid & VALID_POSITION:
            self._reject("no_positions", f"JOINT_FEEDBACK without positions (valid_fields={valid})")
            return None
        if valid < 0 or valid > 15 or group < 0 or group > 3:
            self._reject("bad_header", f"JOINT_FEEDBACK group {group} valid_fields {valid}")
            return None
        if not all(math.isfinite(v) and abs(v) < MAX_ABS_JOINT for v in pos):
            self._reject("bad_value", "JOINT_FEEDBACK with a non-finite or impossible position")
            return None
        self.counters["frames"] += 1
        return JointFeedback(
            group, valid, time, tuple(pos), tuple(vel) if valid & VALID_VELOCITY else None
        )
