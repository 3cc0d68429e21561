"""Force-profile transfer: segmenting a table, its CRC-32, and the device-side reassembly.

A profile table is ``n`` forces in newtons spread evenly over 0..100 % of the gait cycle (point
``k`` at ``100·k/(n−1)`` %); the hip profile uses 101 points (1 % steps). On the wire each force
is a raw unsigned 16-bit count of 0.1 N (``round(force_n / 0.1)``, the DBC's own conversion), three
per :class:`ProfileSegment`, followed by a :class:`ProfileCommit` with ``n`` and the CRC-32.

CRC-32 (documented byte encoding): ``zlib.crc32`` (IEEE 802.3; reflected polynomial 0xEDB88320,
initial value and final xor 0xFFFFFFFF; check value 0xCBF43926 for ``b"123456789"``) over the
``n`` raw counts, each as 2 bytes little-endian, in table order, padding excluded. These are
exactly the Force bytes of the segments in order, so a device can run the CRC over the payload
bytes as they arrive.

:class:`ProfileAssembler` is the device's side of the contract (collect segments, check the
commit, answer ack/nack); the virtual exosuit and the tests use it, a firmware implements the
same checks. Bridge-side safety limits (force, timing, rate of change) are applied before a table
reaches this module; the device's limits here are its own last line of defence.

Multi-actuator table layout (defined here once; PROTOCOL.md, "Force profile tables")
------------------------------------------------------------------------------------
A push carries ONE table. A device whose actuators run different profiles (a hip + ankle suit)
gets them concatenated: ``k`` tables of the same length ``m`` (each over 0..100 % of its own
joint's gait cycle), in the device's table order, so the pushed table has shape ``(k·m,)`` and
point ``j`` of table ``i`` is point ``i·m + j``. The table order is the order of first
appearance of each actuator's load path (joint) in actuator order (:func:`table_order`): a hip
suit, actuators ``("hip", "hip")``, has one table that both legs execute; a hip + ankle suit,
``("hip", "ankle")``, has ``[hip, ankle]``. :func:`pack_tables` builds the table the bridge
sends, :func:`unpack_tables` splits what the device receives; the commit's ``NumPoints`` is
``k·m`` and the CRC runs over all of it, so the device checks the whole set at once and the
actuators switch to their parts from one commit.
"""

from __future__ import annotations

import math
import numbers
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import can
import numpy as np

from drivers.exosuit.codec import (
    EncodeError,
    NackReason,
    ProfileAck,
    ProfileCommit,
    ProfileSegment,
    database,
)

__all__ = [
    "FORCE_RESOLUTION_N",
    "MAX_FORCE_ON_WIRE_N",
    "MAX_PROFILE_POINTS",
    "MIN_PROFILE_POINTS",
    "POINTS_PER_SEGMENT",
    "ProfileAssembler",
    "ProfileTransfer",
    "forces_to_raw",
    "pack_tables",
    "profile_crc32",
    "raw_to_forces",
    "segment_count",
    "table_order",
    "unpack_tables",
]

#: Force resolution on the wire (DBC ProfileSegment.ForceN scale).
FORCE_RESOLUTION_N = 0.1
#: Largest force a uint16 of 0.1 N can carry.
MAX_FORCE_ON_WIRE_N = 6553.5
#: Points carried by one ProfileSegment frame.
POINTS_PER_SEGMENT = 3
#: Table length limits: 2 points at least (0 % and 100 %); 256 segments × 3 points at most
#: (the segment index is 8 bits). A device may support fewer and nack ``bad_length``.
MIN_PROFILE_POINTS = 2
MAX_PROFILE_POINTS = 256 * POINTS_PER_SEGMENT


def segment_count(n_points: int) -> int:
    """Number of ProfileSegment frames for a table of ``n_points`` (ceil(n/3))."""
    return -(-n_points // POINTS_PER_SEGMENT)


def table_order(joints: Sequence[str]) -> tuple[str, ...]:
    """The tables a device with these actuators takes, in wire order (module docstring).

    Args:
        joints: the load path (joint) of each actuator, in actuator order, e.g.
            ``("hip", "hip")`` or ``("hip", "ankle")``.

    Returns:
        The distinct joints in order of first appearance: ``("hip",)``, ``("hip", "ankle")``.

    Raises:
        EncodeError: no actuators, or a joint that is not a non-empty string.
    """
    joints = tuple(joints)
    if not joints or any(not isinstance(j, str) or not j for j in joints):
        raise EncodeError(f"joints {joints!r}; expected one non-empty joint name per actuator")
    return tuple(dict.fromkeys(joints))


def pack_tables(tables: Sequence[Sequence[float] | np.ndarray]) -> np.ndarray:
    """Concatenate per-table forces into the one table a push carries (module docstring).

    Args:
        tables: ``k ≥ 1`` tables in the device's table order (:func:`table_order`), each of
            shape ``(m,)`` with the same ``m ≥ 2``, forces in newtons over 0..100 % gait cycle.

    Returns:
        Shape ``(k·m,)``, float64 newtons: table 0's points, then table 1's, ...

    Raises:
        EncodeError: no tables, a table that is not 1-D, tables of different lengths, fewer
            than 2 points per table, or more than 768 points in all.
    """
    if isinstance(tables, np.ndarray) and tables.ndim == 1:
        raise EncodeError("pack_tables needs a sequence of tables, got one 1-D array")
    arrays = [np.asarray(t, dtype=float) for t in tables]
    if not arrays:
        raise EncodeError("pack_tables: expected at least one table, got none")
    for i, a in enumerate(arrays):
        if a.ndim != 1:
            raise EncodeError(f"pack_tables: table {i} has shape {a.shape}; expected (m,)")
    lengths = {a.size for a in arrays}
    if len(lengths) != 1:
        raise EncodeError(
            f"pack_tables: tables have {[a.size for a in arrays]} points; expected one length m"
        )
    m = lengths.pop()
    if m < MIN_PROFILE_POINTS or m * len(arrays) > MAX_PROFILE_POINTS:
        raise EncodeError(
            f"pack_tables: {len(arrays)} table(s) of {m} points; expected >= "
            f"{MIN_PROFILE_POINTS} points each and <= {MAX_PROFILE_POINTS} in all"
        )
    return np.concatenate(arrays)


def unpack_tables(table: Sequence[float] | Sequence[int] | np.ndarray,
                  n_tables: int) -> tuple[np.ndarray, ...]:
    """Split a received table into its ``n_tables`` parts (the inverse of :func:`pack_tables`).

    Args:
        table: shape ``(k·m,)``, newtons or raw 0.1 N counts (the dtype is kept).
        n_tables: ``k``, the number of tables the device takes (``len(table_order(joints))``).

    Returns:
        ``k`` arrays of shape ``(m,)``, copies, in table order.

    Raises:
        EncodeError: ``n_tables`` is not a positive integer, the table is not 1-D, or its
            length is not ``k·m`` with ``m ≥ 2``.
    """
    if isinstance(n_tables, bool) or not isinstance(n_tables, numbers.Integral) or n_tables < 1:
        raise EncodeError(f"unpack_tables: n_tables={n_tables!r}; expected an integer >= 1")
    arr = np.asarray(table)
    if arr.ndim != 1:
        raise EncodeError(f"unpack_tables: table has shape {arr.shape}; expected (n,)")
    m, rest = divmod(arr.size, int(n_tables))
    if rest or m < MIN_PROFILE_POINTS:
        raise EncodeError(
            f"a table of {arr.size} points does not split into {n_tables} tables of >= "
            f"{MIN_PROFILE_POINTS} points each"
        )
    return tuple(arr[i * m:(i + 1) * m].copy() for i in range(int(n_tables)))


def forces_to_raw(forces_n: Sequence[float] | np.ndarray) -> tuple[int, ...]:
    """Quantise forces (N) to raw 0.1 N counts with the DBC signal's own conversion.

    Raises:
        EncodeError: a force is not finite or outside 0..6553.5 N.
    """
    conversion = database().get_message_by_name("ProfileSegment").get_signal_by_name(
        "Force0"
    ).conversion
    raw = []
    for k, force in enumerate(np.asarray(forces_n, dtype=float).ravel().tolist()):
        if not math.isfinite(force) or not 0.0 <= force <= MAX_FORCE_ON_WIRE_N:
            raise EncodeError(
                f"profile point {k} = {force!r} N; expected a finite force in "
                f"0..{MAX_FORCE_ON_WIRE_N} N"
            )
        raw.append(int(conversion.numeric_scaled_to_raw(force)))
    return tuple(raw)


def raw_to_forces(raw: Sequence[int]) -> tuple[float, ...]:
    """Raw 0.1 N counts back to newtons (the DBC conversion)."""
    conversion = database().get_message_by_name("ProfileSegment").get_signal_by_name(
        "Force0"
    ).conversion
    return tuple(float(conversion.raw_to_scaled(r, decode_choices=False)) for r in raw)


def profile_crc32(raw: Sequence[int]) -> int:
    """CRC-32 of a table of raw counts: zlib.crc32 over each count as uint16 little-endian."""
    return zlib.crc32(struct.pack(f"<{len(raw)}H", *raw))


@dataclass(frozen=True)
class ProfileTransfer:
    """One force-profile table ready for the wire: its segments and its commit.

    Build it with :meth:`from_forces`. ``forces_raw`` are the 0.1 N counts actually sent.

    Attributes:
        version: profile version 1..255 (0 is reserved for "no profile").
        forces_raw: the table as raw 0.1 N counts, length 2..768.
    """

    version: int
    forces_raw: tuple[int, ...]

    def __post_init__(self) -> None:
        version = self.version
        if isinstance(version, bool) or not isinstance(version, numbers.Integral) or not (
            1 <= version <= 255
        ):
            raise EncodeError(f"profile version must be an integer 1..255, got {version!r}")
        object.__setattr__(self, "version", int(version))  # numpy integers become plain ints
        n = len(self.forces_raw)
        if not MIN_PROFILE_POINTS <= n <= MAX_PROFILE_POINTS:
            raise EncodeError(
                f"profile has {n} points; expected {MIN_PROFILE_POINTS}..{MAX_PROFILE_POINTS}"
            )
        bad = [r for r in self.forces_raw if not (isinstance(r, int) and 0 <= r <= 0xFFFF)]
        if bad:
            raise EncodeError(f"raw profile counts must be integers 0..65535, got {bad[0]!r}")

    @classmethod
    def from_forces(cls, forces_n: Sequence[float] | np.ndarray, version: int) -> ProfileTransfer:
        """Quantise a table of forces (N, shape (n,), 0..100 % gait cycle) for transfer.

        Raises:
            EncodeError: bad version, length outside 2..768, NaN/inf or force out of range.
        """
        return cls(version, forces_to_raw(forces_n))

    @property
    def n_points(self) -> int:
        """Number of points in the table."""
        return len(self.forces_raw)

    @property
    def forces_n(self) -> tuple[float, ...]:
        """The table as sent, in newtons (quantised to 0.1 N)."""
        return raw_to_forces(self.forces_raw)

    @property
    def crc32(self) -> int:
        """CRC-32 of the table (see the module docstring for the byte encoding)."""
        return profile_crc32(self.forces_raw)

    def segments(self) -> tuple[ProfileSegment, ...]:
        """The segments, index 0 first; the last one padded with zeros."""
        forces = self.forces_n
        out = []
        for index in range(segment_count(self.n_points)):
            chunk = forces[index * POINTS_PER_SEGMENT:(index + 1) * POINTS_PER_SEGMENT]
            padded = tuple(chunk) + (0.0,) * (POINTS_PER_SEGMENT - len(chunk))
            out.append(ProfileSegment(self.version, index, padded))  # type: ignore[arg-type]
        return tuple(out)

    def commit(self) -> ProfileCommit:
        """The commit that ends the transfer."""
        return ProfileCommit(self.version, self.n_points, self.crc32)

    def frames(self) -> list[can.Message]:
        """All frames of one transfer attempt, in sending order: the segments, then the commit."""
        return [s.to_frame() for s in self.segments()] + [self.commit().to_frame()]


class ProfileAssembler:
    """The device side of a transfer: collect segments, check a commit, answer ack or nack.

    Checks on a commit, in this order (the first failing one is the nack reason):
    busy → BUSY; version 0 → BAD_VERSION; ``n_points`` outside 2..``max_points`` → BAD_LENGTH
    (detail = ``max_points``); a segment 0..ceil(n/3)−1 of that version missing → MISSING_SEGMENT
    (detail = first missing index); CRC mismatch → BAD_CRC; a point above ``max_force_n`` or a
    step between neighbours above ``max_step_n`` → OUT_OF_LIMITS (detail = first offending point).
    A repeated commit of the same table is acked again (a lost ack is harmless).

    Args:
        max_force_n: the device's force limit (N).
        max_step_n: largest allowed change between neighbouring points (N), or None.
        max_points: the longest table the device accepts (≤ 768).
    """

    def __init__(
        self,
        *,
        max_force_n: float,
        max_step_n: float | None = None,
        max_points: int = MAX_PROFILE_POINTS,
    ) -> None:
        if not MIN_PROFILE_POINTS <= max_points <= MAX_PROFILE_POINTS:
            raise EncodeError(
                f"max_points must be {MIN_PROFILE_POINTS}..{MAX_PROFILE_POINTS}, got {max_points}"
            )
        self.max_force_n = float(max_force_n)
        self.max_step_n = None if max_step_n is None else float(max_step_n)
        self.max_points = max_points
        #: Set by the device while it cannot take a profile (fault, calibration).
        self.busy = False
        self._version: int | None = None
        self._segments: dict[int, tuple[int, int, int]] = {}

    @property
    def receiving_version(self) -> int | None:
        """Version of the partial table being received, or None."""
        return self._version

    def on_segment(self, segment: ProfileSegment) -> None:
        """Store one segment; a new version discards the partial table of the previous one."""
        if segment.version != self._version:
            self._version = segment.version
            self._segments = {}
        raw = forces_to_raw(segment.forces_n)
        self._segments[segment.index] = (raw[0], raw[1], raw[2])

    def on_commit(self, commit: ProfileCommit) -> tuple[ProfileAck, tuple[float, ...] | None]:
        """Check a commit against the received segments.

        Returns:
            (the ack or nack to send, the table in newtons if acked else None). On ack the
            device puts the table in its back buffer and switches at the next gait-cycle
            boundary.
        """
        version, n = commit.version, commit.n_points
        if self.busy:
            return ProfileAck.nack(version, NackReason.BUSY), None
        if version == 0:
            return ProfileAck.nack(version, NackReason.BAD_VERSION), None
        if not MIN_PROFILE_POINTS <= n <= self.max_points:
            return ProfileAck.nack(version, NackReason.BAD_LENGTH, self.max_points), None
        needed = segment_count(n)
        have = self._segments if self._version == version else {}
        missing = [i for i in range(needed) if i not in have]
        if missing:
            return ProfileAck.nack(version, NackReason.MISSING_SEGMENT, missing[0]), None
        raw = [r for i in range(needed) for r in have[i]][:n]
        if profile_crc32(raw) != commit.crc32:
            return ProfileAck.nack(version, NackReason.BAD_CRC), None
        forces = raw_to_forces(raw)
        for k, force in enumerate(forces):
            step_bad = (
                self.max_step_n is not None and k > 0
                and abs(force - forces[k - 1]) > self.max_step_n
            )
            if force > self.max_force_n or step_bad:
                return ProfileAck.nack(version, NackReason.OUT_OF_LIMITS, k), None
        return ProfileAck.ack(version), forces
