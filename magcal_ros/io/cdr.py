"""The CDR codec of the array's two message types: one MagneticField decoder for bags and nodes.

``sensor_msgs/msg/MagneticField`` serialises (ROS 2 CDR, after the 4-byte encapsulation
header) as ``int32 sec, uint32 nanosec, uint32 len, frame_id + NUL, pad to 8,
float64[3] field (T), float64[9] covariance``: fixed size except the frame id. A batch of
messages with equal length is therefore one (N, L) byte array whose columns are the
fields, and decoding or encoding a batch costs a few numpy copies instead of one Python
object per message. ``std_msgs/msg/Float64MultiArray`` with the fixed 3x3 layout is
fixed size as a whole.

Templates are produced by rosbags' own serializer at import, so the bytes written are
exactly what ``Typestore.serialize_cdr`` gives (the tests check this).

Current channels (``sensor_msgs/msg/BatteryState`` and ``std_msgs/msg/Float64``, a few per
second), the sensors' temperatures (``sensor_msgs/msg/Temperature``) and the IMU
(``sensor_msgs/msg/Imu``, tens to hundreds per second) go through rosbags' typestore one
message at a time (:func:`decode_current`, :func:`decode_temperature`, :func:`decode_imu`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.stamps import ROS_MAX_SECONDS, split_stamp
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
VECTOR3_STAMPED = "geometry_msgs/msg/Vector3Stamped"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
BATTERY_STATE = "sensor_msgs/msg/BatteryState"
"""A current channel: ``current`` (A) at its header stamp."""
FLOAT64 = "std_msgs/msg/Float64"
"""A current channel: ``data`` (A); no header, so its bag time is its stamp."""
CURRENT_TYPES: tuple[str, ...] = (BATTERY_STATE, FLOAT64)
TEMPERATURE = "sensor_msgs/msg/Temperature"
"""A sensor's temperature: ``temperature`` (deg C) at its header stamp."""
IMU = "sensor_msgs/msg/Imu"
"""The IMU: ``orientation`` (IMU frame to world ENU), ``angular_velocity`` (rad/s, IMU frame)."""
ENCAPSULATION_LE = b"\x00\x01\x00\x00"

F8 = np.dtype("<f8")
U8 = np.uint8


@lru_cache(maxsize=1)
def typestore() -> "Typestore":
    """The ROS 2 Jazzy typestore of rosbags (built once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def magnetic_field_message(sec: int, nanosec: int, frame_id: str, vector: Any, covariance: Any = None) -> Any:
    """A rosbags ``MagneticField`` object (for tests and the plain reference path)."""
    ts = typestore()
    t = ts.types
    return t[MAGNETIC_FIELD](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id),
        magnetic_field=t["geometry_msgs/msg/Vector3"](x=float(vector[0]), y=float(vector[1]), z=float(vector[2])),
        magnetic_field_covariance=np.zeros(9) if covariance is None else np.asarray(covariance, dtype=float),
    )


def vector3_stamped_message(sec: int, nanosec: int, frame_id: str, vector: Any) -> Any:
    """A rosbags ``Vector3Stamped`` object (for templates and tests)."""
    t = typestore().types
    return t[VECTOR3_STAMPED](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id),
        vector=t["geometry_msgs/msg/Vector3"](x=float(vector[0]), y=float(vector[1]), z=float(vector[2])),
    )


def gradient_message(values: Any) -> Any:
    """A rosbags ``Float64MultiArray`` with the 3x3 row-major tensor layout (T/m)."""
    t = typestore().types
    dim = t["std_msgs/msg/MultiArrayDimension"]
    layout = t["std_msgs/msg/MultiArrayLayout"](dim=[dim(label="row", size=3, stride=9), dim(label="col", size=3, stride=3)], data_offset=0)
    return t[FLOAT64_MULTI_ARRAY](layout=layout, data=np.asarray(values, dtype=float).reshape(9))


def battery_state_message(stamp_ns: int, current: float, frame_id: str = "") -> Any:
    """A rosbags ``BatteryState`` carrying ``current`` (A) at ``stamp_ns``; nothing else measured (NaN)."""
    t = typestore().types
    sec, nsec = divmod(int(stamp_ns), NS_PER_S)
    nan = float("nan")
    return t[BATTERY_STATE](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id),
        voltage=nan, temperature=nan, current=float(current), charge=nan, capacity=nan, design_capacity=nan,
        percentage=nan, power_supply_status=0, power_supply_health=0, power_supply_technology=0, present=True,
        cell_voltage=np.zeros(0, np.float32), cell_temperature=np.zeros(0, np.float32), location="", serial_number="",
    )


def decode_current(msgtype: str, data: bytes, bag_time_ns: int) -> tuple[int, float]:
    """Stamp (ns) and current (A) of one serialized current message of type ``msgtype``.

    ``BatteryState``: its header stamp (``bag_time_ns`` when that is zero) and ``current``;
    ``Float64``: ``bag_time_ns`` and
    ``data``. Raises :class:`InputError` for another type or bytes that do not decode.
    """
    if msgtype not in CURRENT_TYPES:
        raise InputError(f"{msgtype} is not a current channel type ({', '.join(CURRENT_TYPES)})")
    try:
        msg = typestore().deserialize_cdr(data, msgtype)
    except Exception as exc:  # rosbags raises several kinds for bytes of another layout
        raise InputError(f"malformed {msgtype} message ({type(exc).__name__})") from None
    if msgtype == FLOAT64:
        return int(bag_time_ns), float(msg.data)
    stamp = int(msg.header.stamp.sec) * NS_PER_S + int(msg.header.stamp.nanosec)
    return stamp or int(bag_time_ns), float(msg.current)  # an unstamped header: the bag time


def _header(stamp_ns: int, frame_id: str) -> Any:
    t = typestore().types
    sec, nsec = divmod(int(stamp_ns), NS_PER_S)
    return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def temperature_message(stamp_ns: int, celsius: float, frame_id: str = "", variance: float = 0.0) -> Any:
    """A rosbags ``Temperature`` of ``celsius`` (deg C) at ``stamp_ns``."""
    return typestore().types[TEMPERATURE](header=_header(stamp_ns, frame_id), temperature=float(celsius),
                                          variance=float(variance))


def imu_message(stamp_ns: int, orientation: Any, angular_velocity: Any, frame_id: str = "") -> Any:
    """A rosbags ``Imu``: ``orientation`` x, y, z, w (IMU frame to ENU) and ``angular_velocity`` (rad/s, IMU
    frame) at ``stamp_ns``; a NaN orientation or angular velocity is sent as unknown (covariance element 0 is
    -1, the values 0, as REP 145 says); no linear acceleration (unknown)."""
    t = typestore().types
    q = np.asarray(orientation, dtype=float).reshape(4)
    w = np.asarray(angular_velocity, dtype=float).reshape(3)
    unknown = np.zeros(9)
    unknown[0] = -1.0
    q_ok, w_ok = bool(np.all(np.isfinite(q))), bool(np.all(np.isfinite(w)))
    if not q_ok:
        q = np.array([0.0, 0.0, 0.0, 1.0])
    if not w_ok:
        w = np.zeros(3)
    return t[IMU](
        header=_header(stamp_ns, frame_id),
        orientation=t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        orientation_covariance=np.zeros(9) if q_ok else unknown,
        angular_velocity=t["geometry_msgs/msg/Vector3"](x=float(w[0]), y=float(w[1]), z=float(w[2])),
        angular_velocity_covariance=np.zeros(9) if w_ok else unknown.copy(),
        linear_acceleration=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        linear_acceleration_covariance=unknown.copy(),
    )


def _deserialize(msgtype: str, data: bytes) -> Any:
    try:
        return typestore().deserialize_cdr(data, msgtype)
    except Exception as exc:  # rosbags raises several kinds for bytes of another layout
        raise InputError(f"malformed {msgtype} message ({type(exc).__name__})") from None


def _stamp(msg: Any, bag_time_ns: int) -> int:
    """A message's header stamp (ns), or its bag time when the header is unstamped."""
    return int(msg.header.stamp.sec) * NS_PER_S + int(msg.header.stamp.nanosec) or int(bag_time_ns)


def decode_temperature(data: bytes, bag_time_ns: int) -> tuple[int, float]:
    """Stamp (ns; the bag time when the header is unstamped) and temperature (deg C) of a serialized Temperature."""
    msg = _deserialize(TEMPERATURE, data)
    return _stamp(msg, bag_time_ns), float(msg.temperature)


def decode_imu(data: bytes, bag_time_ns: int) -> tuple[int, tuple[float, ...], tuple[float, ...], str]:
    """Stamp (ns; the bag time when unstamped), orientation (x, y, z, w; NaN when orientation_covariance[0]
    is -1 or the quaternion is zero), angular velocity (rad/s; NaN when its covariance[0] is -1) and frame_id
    of a serialized Imu."""
    msg = _deserialize(IMU, data)
    o, w = msg.orientation, msg.angular_velocity
    q: tuple[float, ...] = (float(o.x), float(o.y), float(o.z), float(o.w))
    if msg.orientation_covariance[0] == -1.0 or not any(q):
        q = (np.nan,) * 4
    rate: tuple[float, ...] = (float(w.x), float(w.y), float(w.z))
    if msg.angular_velocity_covariance[0] == -1.0:
        rate = (np.nan,) * 3
    return _stamp(msg, bag_time_ns), q, rate, str(msg.header.frame_id)


def _put(out: NDArray[np.uint8], offset: int, values: Any, dtype: str) -> None:
    """Write ``values`` (N, ...) as ``dtype`` into byte columns ``offset..`` of ``out`` (N, B)."""
    if not len(out):  # an empty batch (a stream with no messages): nothing to write
        return
    v = np.ascontiguousarray(np.asarray(values).astype(dtype, copy=False))
    raw = v.view(U8).reshape(len(out), -1)
    out[:, offset : offset + raw.shape[1]] = raw


def _get(buf: NDArray[np.uint8], offset: int, count: int, dtype: np.dtype) -> NDArray[Any]:
    """Read ``count`` values of ``dtype`` from byte columns ``offset..`` of ``buf`` (N, L)."""
    width = count * dtype.itemsize
    return np.ascontiguousarray(buf[:, offset : offset + width]).view(dtype).reshape(len(buf), count)


@dataclass(frozen=True)
class MagneticFieldTemplate:
    """Byte template of a stamped vector message (MagneticField, Vector3Stamped) with a fixed
    ``frame_id``: stamp at 4, the 3 doubles at ``vector_at``."""

    frame_id: str
    template: NDArray[np.uint8]
    vector_at: int

    @property
    def size(self) -> int:
        """Serialized length in bytes."""
        return len(self.template)

    def fill(self, out: NDArray[np.uint8], offset: int, stamp_ns: NDArray[np.int64], vectors: NDArray[np.float64]) -> None:
        """Encode N messages into columns ``offset..offset+size`` of ``out`` (N, B), template already copied."""
        sec, nsec = split_stamp(stamp_ns)
        if len(sec) and (sec.max() > ROS_MAX_SECONDS or sec.min() < -ROS_MAX_SECONDS - 1):
            bad = int(sec.max() if sec.max() > ROS_MAX_SECONDS else sec.min())
            raise InputError(f"stamp {bad} s does not fit a ROS stamp (builtin_interfaces/Time.sec is int32: "
                             f"up to {ROS_MAX_SECONDS} s, 2038-01-19); a bag cannot hold it")
        _put(out, offset + 4, sec, "<i4")
        _put(out, offset + 8, nsec, "<u4")
        _put(out, offset + self.vector_at, vectors, "<f8")

    def encode(self, stamp_ns: NDArray[np.int64], vectors: NDArray[np.float64]) -> NDArray[np.uint8]:
        """(N, size) bytes of N messages, stamps in ns, vectors (N, 3) in T."""
        out = np.empty((len(stamp_ns), self.size), U8)
        out[:] = self.template
        self.fill(out, 0, stamp_ns, vectors)
        return out


@lru_cache(maxsize=64)
def magnetic_field_template(frame_id: str) -> MagneticFieldTemplate:
    """Template for ``frame_id``, built with rosbags' serializer and self-checked."""
    ts = typestore()
    raw = np.frombuffer(bytes(ts.serialize_cdr(magnetic_field_message(0, 0, frame_id, (0, 0, 0)), MAGNETIC_FIELD, little_endian=True)), U8).copy()
    t = MagneticFieldTemplate(frame_id, raw, len(raw) - 96)
    probe = bytes(t.encode(np.array([7 * NS_PER_S + 5]), np.array([[1.5, -2.5, 3.25]]))[0])
    expected = bytes(ts.serialize_cdr(magnetic_field_message(7, 5, frame_id, (1.5, -2.5, 3.25)), MAGNETIC_FIELD, little_endian=True))
    if probe != expected:  # pragma: no cover - guards a change of the CDR layout
        raise RuntimeError("MagneticField byte template does not match rosbags' serializer")
    return t


@lru_cache(maxsize=64)
def vector3_stamped_template(frame_id: str) -> MagneticFieldTemplate:
    """Template of a ``Vector3Stamped`` (stamp at 4, vector last), self-checked like the others."""
    ts = typestore()
    raw = np.frombuffer(bytes(ts.serialize_cdr(vector3_stamped_message(0, 0, frame_id, (0, 0, 0)), VECTOR3_STAMPED,
                                               little_endian=True)), U8).copy()
    t = MagneticFieldTemplate(frame_id, raw, len(raw) - 24)
    probe = bytes(t.encode(np.array([7 * NS_PER_S + 5]), np.array([[1.5, -2.5, 3.25]]))[0])
    expected = bytes(ts.serialize_cdr(vector3_stamped_message(7, 5, frame_id, (1.5, -2.5, 3.25)), VECTOR3_STAMPED,
                                      little_endian=True))
    if probe != expected:  # pragma: no cover - guards a change of the CDR layout
        raise RuntimeError("Vector3Stamped byte template does not match rosbags' serializer")
    return t


@dataclass(frozen=True)
class GradientTemplate:
    """Byte template of the 3x3 ``Float64MultiArray``: 9 doubles at ``data_at``."""

    template: NDArray[np.uint8]
    data_at: int

    @property
    def size(self) -> int:
        """Serialized length in bytes."""
        return len(self.template)

    def fill(self, out: NDArray[np.uint8], offset: int, tensors: NDArray[np.float64]) -> None:
        """Encode N tensors (N, 3, 3) T/m, row-major, into ``out`` at ``offset``."""
        _put(out, offset + self.data_at, np.asarray(tensors).reshape(len(out), 9), "<f8")

    def encode(self, tensors: NDArray[np.float64]) -> NDArray[np.uint8]:
        """(N, size) bytes of N tensor messages."""
        out = np.empty((len(tensors), self.size), U8)
        out[:] = self.template
        self.fill(out, 0, tensors)
        return out


@lru_cache(maxsize=1)
def gradient_template() -> GradientTemplate:
    """Template of the tensor message, built with rosbags' serializer and self-checked."""
    ts = typestore()
    raw = np.frombuffer(bytes(ts.serialize_cdr(gradient_message(np.zeros(9)), FLOAT64_MULTI_ARRAY, little_endian=True)), U8).copy()
    t = GradientTemplate(raw, len(raw) - 72)
    values = np.arange(9.0) - 3.5
    expected = bytes(ts.serialize_cdr(gradient_message(values), FLOAT64_MULTI_ARRAY, little_endian=True))
    if bytes(t.encode(values.reshape(1, 3, 3))[0]) != expected:  # pragma: no cover
        raise RuntimeError("Float64MultiArray byte template does not match rosbags' serializer")
    return t


def _decode_group(buf: NDArray[np.uint8], little: bool, what: str) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Decode equal-length MagneticField messages (N, L) of one endianness."""
    e = "<" if little else ">"
    n, length = buf.shape
    sec = _get(buf, 4, 1, np.dtype(e + "i4"))[:, 0].astype(np.int64)
    nsec = _get(buf, 8, 1, np.dtype(e + "u4"))[:, 0].astype(np.int64)
    slen = _get(buf, 12, 1, np.dtype(e + "u4"))[:, 0].astype(np.int64)
    # CDR alignment counts from the end of the encapsulation header; like rosbags, accept
    # up to 3 bytes of trailing padding.
    vector_at = 4 + ((12 + slen + 7) // 8) * 8
    extra = length - vector_at - 96
    if np.any(extra < 0) or np.any(extra > 3) or np.any(vector_at != vector_at[0]) or np.any(nsec >= NS_PER_S):
        raise InputError(f"{what}: malformed sensor_msgs/MagneticField message (length {length} bytes)")
    vec = _get(buf, int(vector_at[0]), 3, np.dtype(e + "f8")).astype(float)
    return sec * NS_PER_S + nsec, vec


def decode_magnetic_field_rows(buf: NDArray[np.uint8], what: str = "bag") -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Header stamps (N,) ns and vectors (N, 3) T of equal-length MagneticField messages (N, L)."""
    if len(buf) == 0:
        return np.empty(0, np.int64), np.empty((0, 3))
    if buf.shape[1] < 4 + 16 + 96:
        raise InputError(f"{what}: message too short for sensor_msgs/MagneticField")
    _check_encapsulation(buf, what)
    kinds = buf[:, 1]
    if np.all(kinds == kinds[0]):
        return _decode_group(buf, bool(kinds[0] == 1), what)
    stamps, vectors = np.empty(len(buf), np.int64), np.empty((len(buf), 3))
    for kind in (0, 1):
        idx = np.flatnonzero(kinds == kind)
        stamps[idx], vectors[idx] = _decode_group(buf[idx], kind == 1, what)
    return stamps, vectors


def decode_magnetic_fields(messages: list[bytes], what: str = "bag") -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Header stamps (N,) ns and field vectors (N, 3) T of serialized MagneticField messages.

    Vectorised over messages of equal length (one group per distinct frame id length).
    Raises :class:`InputError` for messages that are not MagneticField.
    """
    n = len(messages)
    if n == 0:
        return np.empty(0, np.int64), np.empty((0, 3))
    lengths = np.fromiter(map(len, messages), dtype=np.int64, count=n)
    blob = np.frombuffer(b"".join(messages), U8)
    if np.all(lengths == lengths[0]):
        return decode_magnetic_field_rows(blob.reshape(n, int(lengths[0])), what)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    stamps = np.empty(n, np.int64)
    vectors = np.empty((n, 3))
    for length in np.unique(lengths):
        idx = np.flatnonzero(lengths == length)
        stamps[idx], vectors[idx] = decode_magnetic_field_rows(blob[starts[idx, None] + np.arange(length)], what)
    return stamps, vectors


def _check_encapsulation(buf: NDArray[np.uint8], what: str) -> None:
    if np.any(buf[:, 0] != 0) or np.any(buf[:, 1] > 1):
        raise InputError(f"{what}: message is not plain CDR (encapsulation {bytes(buf[0, :2]).hex()})")


_HEAD = {1: struct.Struct("<iII"), 0: struct.Struct(">iII")}
_VEC3 = {1: struct.Struct("<3d"), 0: struct.Struct(">3d")}


def decode_magnetic_field(data: bytes) -> tuple[int, float, float, float]:
    """Header stamp (ns) and field (T) of one serialized MagneticField (the live nodes' hot path).

    The same layout as :func:`decode_magnetic_fields`, read with :mod:`struct` for a single
    message (no numpy per call). Raises :class:`InputError` for anything else.
    """
    if len(data) < 4 + 16 + 96 or data[0] != 0 or data[1] > 1:
        raise InputError("not a plain CDR sensor_msgs/MagneticField message")
    head, vec = _HEAD[data[1]], _VEC3[data[1]]
    sec, nsec, length = head.unpack_from(data, 4)
    at = 4 + ((12 + length + 7) & ~7)
    if nsec >= NS_PER_S or not 0 <= len(data) - at - 96 <= 3:
        raise InputError("malformed sensor_msgs/MagneticField message")
    x, y, z = vec.unpack_from(data, at)
    return sec * NS_PER_S + nsec, x, y, z


# --------------------------------------------------------------------------- single messages for live publishers

JOINT_STATE = "sensor_msgs/msg/JointState"


class StampedVectorPacker:
    """One stamped vector message (``MagneticField`` or ``Vector3Stamped``) as CDR bytes per call, for a
    live publisher's ``publish(bytes)`` (no message object, no serialisation): frame and covariance fixed
    (from ``template`` and ``covariance``, 9 numbers T^2 row-major, MagneticField only), stamp (ns) and
    vector (T) given."""

    __slots__ = ("_struct", "_head", "_middle", "_tail")

    def __init__(self, template: MagneticFieldTemplate, covariance: Any = None) -> None:
        raw = template.template.tobytes()
        at = template.vector_at
        tail = raw[at + 24 :]
        if covariance is not None:
            if len(tail) != 72:
                raise ValueError("a covariance needs a MagneticField template")
            tail = struct.pack("<9d", *np.asarray(covariance, dtype=float).reshape(9).tolist())
        self._head, self._middle, self._tail = raw[:4], raw[12:at], tail
        self._struct = struct.Struct(f"<4siI{at - 12}s3d{len(tail)}s")

    def pack(self, stamp_ns: int, x: float, y: float, z: float) -> bytes:
        """The serialized message of stamp ``stamp_ns`` (ns) and vector ``x, y, z`` (T)."""
        sec, nsec = divmod(stamp_ns, NS_PER_S)
        return self._struct.pack(self._head, sec, nsec, self._middle, x, y, z, self._tail)


class GradientPacker:
    """The 3x3 ``Float64MultiArray`` (row-major, T/m) as CDR bytes per call (see :class:`StampedVectorPacker`)."""

    __slots__ = ("_struct", "_head")

    def __init__(self, template: GradientTemplate) -> None:
        raw = template.template.tobytes()
        self._head = raw[: template.data_at]
        self._struct = struct.Struct(f"<{template.data_at}s9d")

    def pack(self, values: Any) -> bytes:
        """The serialized message of the nine components ``values`` (T/m, row-major)."""
        return self._struct.pack(self._head, *values)


class StampedNinePacker:
    """A ``JointState`` with nine fixed ``names`` and ``frame_id``: stamp (ns) and the nine ``position``
    values per call, as CDR bytes (``velocity`` and ``effort`` empty; see :class:`StampedVectorPacker`)."""

    __slots__ = ("_struct", "_head", "_middle", "_tail")

    def __init__(self, frame_id: str, names: Any) -> None:
        ts = typestore()
        t = ts.types
        names = list(names)
        if len(names) != 9:
            raise ValueError("nine names")
        probe = (np.arange(9.0) + 1.0) * 1.0009765625  # exact in binary, found once in the bytes below
        msg = t[JOINT_STATE](header=_header(0, frame_id), name=names, position=probe, velocity=np.zeros(0),
                             effort=np.zeros(0))
        raw = bytes(ts.serialize_cdr(msg, JOINT_STATE, little_endian=True))
        at = raw.find(struct.pack("<9d", *probe.tolist()))
        if at < 0 or raw.find(struct.pack("<9d", *probe.tolist()), at + 1) >= 0:  # pragma: no cover
            raise RuntimeError("JointState position not found in its serialized bytes")
        self._head, self._middle, self._tail = raw[:4], raw[12:at], raw[at + 72 :]
        self._struct = struct.Struct(f"<4siI{at - 12}s9d{len(self._tail)}s")

    def pack(self, stamp_ns: int, values: Any) -> bytes:
        """The serialized message of stamp ``stamp_ns`` (ns) and the nine ``values``."""
        sec, nsec = divmod(stamp_ns, NS_PER_S)
        return self._struct.pack(self._head, sec, nsec, self._middle, *values, self._tail)
