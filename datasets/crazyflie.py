"""Crazyflie SD-card binary log (the uSD-card deck's event log) -> :class:`Flight`.

No maintained library reads this format (Bitcraze ship a 90-line example script,
``tools/usdlog/cfusdlog.py``, that prints on errors and reads record by record); the decoder is
written here, with one-line :class:`FlightFormatError` messages naming the file and the byte
offset or record.

Format (little-endian; README of ``../shared/data/real/crazyflie_util_flowdeck``):

* byte 0: magic ``0xBC``; ``uint16`` version (1 or 2); ``uint16`` number of event types;
* per event type: ``uint16`` id, a NUL-terminated name, ``uint16`` number of fields, and per
  field a NUL-terminated ``name(t)`` where ``t`` is a Python ``struct`` type code;
* records until the last 4 bytes: ``uint16`` event id, a time stamp (version 1: ``uint32`` ms,
  version 2: ``uint64`` us, both on the vehicle's clock since boot), then the event's fields
  packed with their type codes (no padding);
* the last 4 bytes: CRC-32 (zlib) of every byte before them.

Decoding: the header is parsed field by field; the record boundaries are found by one pass over
the event ids (each id has a fixed record size), then every event type is decoded at once as a
numpy structured array (one gather of its records' bytes, viewed with a dtype built from the
type codes). A 3.3 MB log (164k records) decodes in about 0.05-0.1 s.

Mapping to fgnav (events of the Crazyflie firmware's ``estimator.c``, as logged by the UTIL
data set; field names as the README gives them):

* ``estGyroscope`` (``gyro.x/y/z`` deg/s) + ``estAcceleration`` (``acc.x/y/z`` g) ->
  ``flight.imu``: body FLU (the Crazyflie's body frame is x forward, y left, z up), deg/s ->
  rad/s, g -> m/s^2 with :data:`FIRMWARE_GRAVITY` (``GRAVITY_MAGNITUDE`` = 9.81 of the firmware's
  ``physicalConstants.h``: the firmware scales its accelerometer to read 1 g at rest and its
  estimator multiplies by this constant). Both are logged per IMU read, the accelerometer 20-60 us
  before the gyro; each gyro sample is paired with the nearest accelerometer sample within
  :data:`IMU_PAIR_TOLERANCE_S` (not interpolated: the shift is < 6 % of a sample period), at the
  gyro's time. Unpaired samples and implausible ones (beyond :data:`.types.IMU_MAX_RATE` /
  :data:`.types.IMU_MAX_ACCEL`: corrupted values) are left out and counted.
* ``estFlow`` (``motion.deltaX/Y``: PMW3901 counts) -> ``flight.flow``. The firmware's driver
  (``flowdeck_v1v2.c``) swaps and negates the axes (its model's x count is ``-deltaY``, its y
  count ``-deltaX``) and its model (``kalman_core/mm_flow.c``) takes the counts as 10x the
  motion pixels (``FLOW_RESOLUTION`` 0.1) with ``Npix / thetapix`` = 35 / 0.71674 pixels per
  radian. Its model counts are ``NX = k dt (v_x cos / h - w_y)``, ``NY = k dt (v_y cos / h +
  w_x)`` in body FLU; fgnav's flow sensor frame (``DOWNWARD_FLOW``: x forward, y right, z down)
  has ``flow = k dt [-v_x / d - w_y, -v_y / d + w_x]`` in sensor axes, i.e. ``[-NX, NY]``, so
  ``flow = 0.1 * [deltaY, -deltaX]``; the firmware's ``35 / 0.71674`` = 48.83 pixels per
  radian reads velocities 2.2 % small, so ``calib.flow_pixels_per_rad`` is the 47.8 fitted
  against Vicon (:data:`FLOW_PIXELS_PER_RAD`).
  Integration interval: not logged. The firmware reads the sensor every ``vTaskDelay(10)``
  (about 9.9 ms) and enqueues (logs) only reads with valid motion; the sensor clears its counts
  on a read, so the current driver takes one loop as the interval of every sample (its 2021
  version took the time since the previous valid sample). ``dt`` is the step from the previous
  logged sample when that step is at most :data:`FLOW_GAP_FACTOR` loops, else one loop; the loop
  period is the median step of the file.
  Samples after a gap (and the first one) are counted in ``meta["flow"]``; a sample is after a
  gap exactly when ``t[i] - t[i-1] > dt[i]``. Measured against Vicon on the seven UTIL flights
  (``downward_check.flow_vs_truth``, scale fitted on the consecutive samples): one loop predicts
  the after-gap samples better than the step since the previous logged sample (residual 0.17-0.24
  against 0.19-0.25 px on every flight), but they carry 1.28-1.46 loops of motion on average
  (1.3 after 2-loop steps, 1.6 after 3-loop steps on traj1): some reads in a gap do not clear
  the counts. Their interval is therefore uncertain by about 30 %; a factor may down-weight them.
  Samples of :data:`FLOW_MAX_COUNTS` counts or more (corrupted) are left out and counted.
* ``estTOF`` (``range.zrange`` mm, VL53L1x pointing down) -> ``flight.range`` in m. Readings of
  0 mm (no valid target: seen on the ground and at landing) and of :data:`TOF_PLAUSIBLE_MAX_M`
  or more (65535 mm: no reading) are left out and counted; other
  readings outside ``[range_min, range_max]`` are kept (the range factor gates them) and counted.
* ``estPose`` (``locSrv.x/y/z`` m, ``locSrv.qx/qy/qz/qw``: the Vicon pose streamed to the
  vehicle) -> ``flight.ground_truth`` (quaternion reordered to ``[w, x, y, z]`` and
  renormalised from float32). Exact repeats of the previous pose (the same values logged again)
  are left out and counted. ``world_v_body`` is derived (not logged): the centred
  Savitzky-Golay derivative of the positions over :data:`GT_VELOCITY_WINDOW_S` (the positions
  are quantised to 1 mm; README: differentiate only after a low-pass). Poses are stamped on
  arrival, about 2 ms after the IMU (README: -1.8 +/- 1.5 ms against the gyro); this reader does
  not shift them (``meta["ground_truth"]``).
* ``estBarometer`` (``baro.asl`` m): fgnav has no barometer stream; a summary goes to
  ``meta["barometer"]`` (:func:`decode_crazyflie_log` gives the samples).
* Every other event type (UWB ``estTDOA``, ...) is counted in ``meta["crazyflie_events"]``.

Time: every stamp in float seconds on the log's own clock (``t = stamp_us * 1e-6``, version 1
``stamp_ms * 1e-3``). Samples whose time does not increase within a stream are left out and
counted.

Calibration (``flight.calib``):

* ``body_T_range``: beam along body -z (``DOWNWARD_RANGE``), lever arm ``(0, 0,``
  :data:`TOF_LEVER_Z` ``)``: the time-of-flight reads :data:`TOF_LEVER_Z` less than the Vicon
  height over the floor (README: scale 1.00, offset about -40 mm; this reader's tests measure it
  per flight). With a body-fixed beam and 2-5 deg of tilt a lever arm along z and a constant
  sensor offset are indistinguishable (both add a constant to the range); the ground-height
  variable absorbs any remainder. Limits :data:`TOF_RANGE_MIN_M` .. :data:`TOF_RANGE_MAX_M`.
* ``body_T_flow``: ``DOWNWARD_FLOW`` rotation at the same point (the PMW3901 and the VL53L1x sit
  side by side on the flow deck, under the body centre).
* ``imu_noise``: :data:`CRAZYFLIE_IMU_NOISE`, the IMU's noise **in flight** (rotor vibration,
  measured against Vicon on the airborne parts of the seven UTIL flights), the figures an
  estimator must assume. The sensor's own densities, with the motors off (:data:`STILL_IMU_NOISE`,
  10-25x lower), are measured on the still starts (50-100 ms each, 50 blocks pooled) as the std
  of 10 ms block means times sqrt(10 ms) (blocks longer than the correlation of the firmware's
  80 Hz / 30 Hz low-pass filters); the same estimate on the file's own still start (5-10 blocks,
  so +/- 30-50 %) is in ``meta["imu_noise"]``. In flight the horizontal accelerometer channels
  are dominated by vibration offsets (README: std 1.2-4 m/s^2, offsets of 1-5 m/s^2 that are
  absent on the ground), which no white-noise density describes: the graph's accelerometer check
  (``fgnav.solvers.accel_check``) finds them and predicts with the thrust axis only.
* ``flow_pixels_per_rad``: :data:`FLOW_PIXELS_PER_RAD` = 47.8, measured against Vicon (README),
  not the firmware's 48.83 (:data:`FIRMWARE_FLOW_PIXELS_PER_RAD`).
"""

from __future__ import annotations

import dataclasses
import logging
import re
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ._files import existing_file
from ._tables import clock_reset, increasing_mask
from .errors import FlightFormatError
from .geometry import make_pose, velocity_from_positions
from .types import (
    DOWNWARD_FLOW,
    DOWNWARD_RANGE,
    IMU_MAX_ACCEL,
    IMU_MAX_RATE,
    Calibration,
    Flight,
    FlowSeries,
    ImuNoise,
    ImuSeries,
    RangeSeries,
    Trajectory,
    imu_plausible,
)

log = logging.getLogger(__name__)

MAGIC = 0xBC
"""Byte 0 of every Crazyflie SD-card log."""
STAMP_DTYPES = {1: ("<u4", 1e-3), 2: ("<u8", 1e-6)}
"""Version -> (time stamp dtype, seconds per stamp unit): v1 ``uint32`` ms, v2 ``uint64`` us."""
CRC_BYTES = 4

STRUCT_CODES = {
    "b": "i1",
    "B": "u1",
    "?": "?",
    "c": "S1",
    "h": "<i2",
    "H": "<u2",
    "i": "<i4",
    "I": "<u4",
    "l": "<i4",
    "L": "<u4",
    "q": "<i8",
    "Q": "<u8",
    "e": "<f2",
    "f": "<f4",
    "d": "<f8",
}
"""Python ``struct`` type codes (standard sizes, as in ``struct.calcsize('<' + code)``) -> numpy
dtypes."""

_FIELD_SPEC = re.compile(r"^(?P<name>.+)\((?P<code>.)\)$")

DEG_TO_RAD = np.pi / 180.0
FIRMWARE_GRAVITY = 9.81
"""m/s^2 per g: ``GRAVITY_MAGNITUDE`` of the Crazyflie firmware (``physicalConstants.h``)."""
FLOW_RESOLUTION = 0.1
"""Motion pixels per PMW3901 count (``FLOW_RESOLUTION`` of ``kalman_core/mm_flow.c``)."""
FIRMWARE_FLOW_NPIX = 35.0
FIRMWARE_FLOW_THETAPIX = 0.71674
"""``Npix`` [px] and ``thetapix`` [rad] of ``mm_flow.c``: 35 pixels across ``2 sin(42 deg / 2)``."""
FIRMWARE_FLOW_PIXELS_PER_RAD = FIRMWARE_FLOW_NPIX / FIRMWARE_FLOW_THETAPIX
"""48.83 px/rad: the firmware's flow scale."""
FLOW_PIXELS_PER_RAD = 47.8
"""Pixels per radian of image motion of the UTIL flow decks, fitted against Vicon (README of
``crazyflie_util_flowdeck``: 47.8 +/- 0.3 pooled over the seven flights; per flight and axis 42-50,
lower on the faster flights); the firmware's 48.83 reads every velocity 2.2 % too small."""
FLOW_RATE_GAIN = (1.1315, -0.2358)
"""``calib.flow_rate_gain`` ``(a, b)``: the UTIL flow decks read an image rate ``r`` [rad/s] as
``(a + b |r|) r`` times :data:`FLOW_PIXELS_PER_RAD`, fitted (least squares, airborne readings,
``r`` the total rate, translation from Vicon velocity and height plus the gyro's rotation) on
the seven flights pooled (2026-12-02, ``cf17b``). The single linear scale of each flight was
0.90-1.05 and fell with the flight's speed (rates 0.4-1.0 rad/s; within traj3 0.91 at 0.6-0.9
and 0.82 at 0.9-1.2 rad/s): the sensor under-reads fast image motion. Fitted leaving each flight
out, the model leaves that flight's scale error at 0.1-5.5 % (3.7-10.4 % with the linear
scale). Gain 1 at 0.56 rad/s."""
FLOW_GAP_FACTOR = 1.5
"""A flow step longer than this many loop periods has dropped reads: ``dt`` is one loop."""
IMU_PAIR_TOLERANCE_S = 0.5e-3
"""Largest gyro-accelerometer stamp difference paired into one IMU sample (half a 1 kHz period)."""
TOF_LEVER_Z = -0.039
"""Range offset as a lever arm along body z [m]: mean of ``range - z / cos(tilt)`` against the
Vicon height over the floor (z = 0) on the seven UTIL flights, -36 to -41 mm per flight
(``downward_check.range_vs_truth``; README: about -40 mm)."""
TOF_RANGE_MIN_M = 0.04
TOF_RANGE_MAX_M = 4.0
"""VL53L1X datasheet ranging interval (4 cm to 4 m; the firmware runs it in medium distance mode
with a 25 ms budget and drops readings >= 5 m)."""
TOF_PLAUSIBLE_MAX_M = 5.0
"""A ToF reading at or above this [m] is not a reading (the firmware drops readings >= 5 m before
its estimator sees them; 65535 mm, the ``uint16`` maximum, is the VL53L1x's 'no reading'): left
out and counted (``skipped_implausible``). Readings in ``(TOF_RANGE_MAX_M, 5 m)`` are kept and
counted (``outside_min_max_kept``): the range factor gates them."""
FLOW_MAX_COUNTS = 1000
"""A flow sample with ``|motion.deltaX|`` or ``|motion.deltaY|`` at or above this many counts
(100 motion pixels in one 10 ms read; the seven UTIL flights stay below 100 counts, and -32768,
the ``int16`` minimum, is no count) is corrupted: left out and counted (``skipped_implausible``)."""
STILL_MIN_S = 0.05
"""Shortest still window used for the IMU noise densities [s]."""
STILL_GYRO_STD_DEG_S = 1.0
"""A 50 ms window is still when every gyro axis' std is below this [deg/s] (motors off: 0.3-0.5,
motors spinning on the ground: 3-20)."""
NOISE_BLOCK_S = 0.01
"""Block length of the noise-density estimate [s]."""
STILL_IMU_NOISE = ImuNoise(gyro_noise_density=1.7e-4, accel_noise_density=2.4e-3)
"""BMI088 on the Crazyflie 2.1 with the motors off, measured on the UTIL logs' still starts
(module docstring): gyro 1.7e-4 rad/s/sqrt(Hz) (axes 1.0, 2.0, 1.9e-4), accel 2.4e-3
m/s^2/sqrt(Hz) (2.0, 3.4, 1.1e-3)."""
#: Gyro bias left in the logged rates [rad/s]: the firmware subtracts the bias it measures at
#: rest before it queues the rates to its estimator (``sensors_bmi088_bmp3xx.c``,
#: ``processGyroBias``), and ``estGyroscope`` logs those queued rates; against Vicon the seven
#: flights' in-flight bias is 0-3.3 mrad/s per axis (1 s blocks, airborne parts). The motors spin
#: up within 0.25 s of the log's start and the vehicle rocks and turns by 20-50 mrad on its legs
#: before take-off, so the log's own ground segment does not measure it better.
CRAZYFLIE_GYRO_BIAS_SIGMA = 3.0e-3
CRAZYFLIE_IMU_NOISE = ImuNoise(
    gyro_noise_density=2.0e-3,
    accel_noise_density=0.06,
    gyro_random_walk=STILL_IMU_NOISE.gyro_random_walk,
    accel_random_walk=0.02,
    gyro_bias_sigma=CRAZYFLIE_GYRO_BIAS_SIGMA,
    rest_bias_removed=True,
)
"""The same IMU **in flight** (``calib.imu_noise``; the estimator's noise model), measured on the
airborne parts of the seven UTIL flights (above 0.3 m): white densities from the differences of
consecutive 10 ms block means (removes the motion): gyro 1.9-2.1e-3 rad/s/sqrt(Hz) on x, y
(0.8e-3 on z), accelerometer z 0.033-0.045 at 10 ms and, against the Vicon specific force,
0.055-0.069 m/s^2/sqrt(Hz) at 50 ms-1 s: rotor vibration, 10-25x the still figures. The z
accelerometer's error against Vicon wanders by about 0.1 m/s^2 over 10 s (random walk 0.02
m/s^3/sqrt(Hz)); the gyro's walk is fgnav's default (the flights are too short to measure it).
The horizontal channels are far worse (offsets of 1-5 m/s^2 in flight): see
``fgnav.solvers.accel_check``."""

GT_VELOCITY_WINDOW_S = 0.1
GT_VELOCITY_RATE_HZ = 300.0
"""Ground-truth velocity: centred Savitzky-Golay derivative over 0.1 s on a 300 Hz resampling of
the Vicon positions (:func:`.geometry.velocity_from_positions`)."""

IMU_EVENTS = ("estGyroscope", "estAcceleration")
GYRO_FIELDS = ("gyro.x", "gyro.y", "gyro.z")
ACCEL_FIELDS = ("acc.x", "acc.y", "acc.z")
FLOW_FIELDS = ("motion.deltaX", "motion.deltaY")
TOF_FIELD = "range.zrange"
POSE_FIELDS = (
    "locSrv.x",
    "locSrv.y",
    "locSrv.z",
    "locSrv.qx",
    "locSrv.qy",
    "locSrv.qz",
    "locSrv.qw",
)
BARO_FIELD = "baro.asl"
READ_EVENTS = ("estGyroscope", "estAcceleration", "estFlow", "estTOF", "estPose", "estBarometer")

STAMP = "_stamp"
"""Name of the time stamp column in the decoded record arrays (field names contain dots, never a
leading underscore)."""


# ----------------------------------------------------------------------------------------------
# Decoder
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EventType:
    """One event type of the header.

    Attributes:
        id: event id of its records.
        name: event name, e.g. ``"estGyroscope"``.
        fields: ``(field name, struct type code)`` per field, in record order.
        offset: byte offset of its definition in the file.
    """

    id: int
    name: str
    fields: tuple[tuple[str, str], ...]
    offset: int

    def payload_dtype(self) -> np.dtype:
        """Packed numpy dtype of the event's fields (no time stamp, no id)."""
        return np.dtype([(n, STRUCT_CODES[c]) for n, c in self.fields])


@dataclass(frozen=True, eq=False)
class CrazyflieLog:
    """A decoded log: header and one structured array of records per event type.

    Attributes:
        path: the file.
        version: 1 or 2.
        event_types: the header's event types, by id.
        records: event name -> structured array with the stamp column :data:`STAMP` (raw units)
            and one column per field (names as in the header, e.g. ``"gyro.x"``); every type of
            the header has an entry (empty when it has no records).
        n_records: number of records in the file.
        header_bytes: size of the header (offset of the first record).
        damage: None for an intact file; for a damaged one decoded with ``check_crc=False``,
            what was found and what was left: ``crc`` (the mismatch), ``stopped_at_byte``,
            ``reason`` (why decoding stopped there, or None when it reached the end) and
            ``bytes_dropped``.
    """

    path: Path
    version: int
    event_types: dict[int, EventType]
    records: dict[str, np.ndarray]
    n_records: int
    header_bytes: int
    damage: dict[str, Any] | None = None

    @property
    def seconds_per_stamp(self) -> float:
        return STAMP_DTYPES[self.version][1]

    def time_s(self, event: str) -> np.ndarray:
        """Stamps of ``event`` in float seconds on the log's clock."""
        return self.require(event)[STAMP].astype(np.float64) * self.seconds_per_stamp

    def require(self, event: str, fields: tuple[str, ...] = ()) -> np.ndarray:
        """The records of ``event``; an error naming the file when the header lacks the event or
        one of ``fields``."""
        if event not in self.records:
            raise FlightFormatError(
                self.path,
                f"no event type {event!r} in the header; it has: {', '.join(self.records)}",
            )
        rec = self.records[event]
        missing = [f for f in fields if f not in rec.dtype.names]
        if missing:
            have = [n for n in rec.dtype.names if n != STAMP]
            raise FlightFormatError(
                self.path,
                f"event {event!r} has no field(s) {missing}; its fields: {', '.join(have)}",
            )
        return rec

    def counts(self) -> dict[str, int]:
        """Records per event name (header order)."""
        return {name: int(len(r)) for name, r in self.records.items()}


def _u16(data: bytes, off: int, path: Path, what: str) -> int:
    if off + 2 > len(data):
        raise FlightFormatError(
            path, f"bad header: file ends at byte {len(data)} while reading {what} at byte {off}"
        )
    return data[off] | (data[off + 1] << 8)


def _cstring(data: bytes, off: int, end: int, path: Path, what: str) -> tuple[str, int]:
    nul = data.find(b"\0", off, end)
    if nul < 0:
        raise FlightFormatError(
            path, f"bad header: {what} at byte {off} has no terminating NUL before byte {end}"
        )
    try:
        return data[off:nul].decode("ascii"), nul + 1
    except UnicodeDecodeError:
        raise FlightFormatError(
            path, f"bad header: {what} at byte {off} is not ASCII text ({data[off:nul][:40]!r})"
        ) from None


def parse_header(
    data: bytes, path: str | Path = "<bytes>"
) -> tuple[int, dict[int, EventType], int]:
    """Parse the header of a log held in ``data``.

    Returns:
        ``(version, event types by id, offset of the first record)``.

    Raises:
        FlightFormatError: naming ``path`` and the byte offset: too short, wrong magic byte,
            unknown version, or a malformed event type definition.
    """
    path = Path(path)
    if len(data) < 5 + CRC_BYTES:
        raise FlightFormatError(
            path,
            f"bad header: {len(data)} bytes is too short for a Crazyflie log (magic, "
            f"version, type count and CRC need {5 + CRC_BYTES})",
        )
    if data[0] != MAGIC:
        raise FlightFormatError(
            path, f"bad header: byte 0 is 0x{data[0]:02X}, not the Crazyflie log magic 0x{MAGIC:X}"
        )
    version = _u16(data, 1, path, "the version")
    if version not in STAMP_DTYPES:
        raise FlightFormatError(
            path,
            f"unknown version {version} at byte 1; supported: "
            + ", ".join(str(v) for v in STAMP_DTYPES),
        )
    n_types = _u16(data, 3, path, "the number of event types")
    end = len(data) - CRC_BYTES
    off = 5
    types: dict[int, EventType] = {}
    names: set[str] = set()
    for k in range(n_types):
        start = off
        eid = _u16(data, off, path, f"the id of event type {k}")
        name, off = _cstring(data, off + 2, end, path, f"the name of event type {k} (id {eid})")
        if not name:
            raise FlightFormatError(
                path, f"bad header: event type {k} (id {eid}) at byte {start} has an empty name"
            )
        if eid in types or name in names:
            raise FlightFormatError(
                path,
                f"bad header: event type {k} at byte {start} repeats id {eid} or name {name!r}",
            )
        n_fields = _u16(data, off, path, f"the field count of event {name!r}")
        off += 2
        fields = []
        for j in range(n_fields):
            spec_at = off
            spec, off = _cstring(data, off, end, path, f"field {j} of event {name!r}")
            m = _FIELD_SPEC.match(spec)
            if m is None:
                raise FlightFormatError(
                    path,
                    f"bad header: field {j} of event {name!r} at byte {spec_at} is "
                    f"{spec!r}, expected 'name(t)' with a struct type code t",
                )
            if m["code"] not in STRUCT_CODES:
                raise FlightFormatError(
                    path,
                    f"bad header: field {m['name']!r} of event {name!r} at byte {spec_at} "
                    f"has type code {m['code']!r}; known: {''.join(STRUCT_CODES)}",
                )
            if m["name"] in (f for f, _ in fields) or m["name"] in (STAMP, "_id"):
                raise FlightFormatError(
                    path,
                    f"bad header: field {m['name']!r} of event {name!r} at byte {spec_at} "
                    "is repeated or reserved",
                )
            fields.append((m["name"], m["code"]))
        types[eid] = EventType(id=eid, name=name, fields=tuple(fields), offset=start)
        names.add(name)
    return version, types, off


SALVAGE_HINT = (
    "; `check_crc = false` in a manifest's table of this log reads the records before the damage"
)
"""Appended to a CRC mismatch: how to salvage the file (:func:`decode_crazyflie_log`)."""


def _crc_problem(data: bytes) -> str | None:
    stored = struct.unpack_from("<I", data, len(data) - CRC_BYTES)[0]
    computed = zlib.crc32(memoryview(data)[: len(data) - CRC_BYTES])
    if stored == computed:
        return None
    return (
        f"CRC-32 mismatch: the last 4 bytes hold 0x{stored:08X}, bytes 0..{len(data) - 5} give "
        f"0x{computed:08X} (damaged or truncated file)"
    )


def _record_starts(
    data: bytes,
    version: int,
    types: dict[int, EventType],
    first: int,
    path: Path,
    salvage: bool = False,
) -> tuple[np.ndarray, np.ndarray, tuple[int, str] | None]:
    """Offsets and ids of every record (one pass over the ids; each id has a fixed size) up to
    the CRC, and None. A record that cannot be read (unknown id, cut off) is an error; with
    ``salvage`` (a file whose CRC does not match: its end may be records) every byte may be a
    record and that record ends the pass, its ``(offset, reason)`` returned third."""
    head = 2 + np.dtype(STAMP_DTYPES[version][0]).itemsize
    size = [0] * 65536
    for e in types.values():
        size[e.id] = head + e.payload_dtype().itemsize
    end = len(data) if salvage else len(data) - CRC_BYTES
    stop = None
    starts: list[int] = []
    ids: list[int] = []
    add_start, add_id = starts.append, ids.append
    off = first
    while off < end:
        problem = None
        if off + 2 > end:
            problem = (
                f"truncated record {len(starts)} at byte {off}: 1 byte left before the CRC, "
                "a record needs at least its 2-byte event id"
            )
        else:
            eid = data[off] | (data[off + 1] << 8)
            n = size[eid]
            if n == 0:
                problem = (
                    f"unknown event id {eid} in record {len(starts)} at byte {off}; the header "
                    f"defines ids {sorted(types)}"
                )
            elif off + n > end:
                problem = (
                    f"truncated record {len(starts)} at byte {off}: event "
                    f"{types[eid].name!r} needs {n} bytes, {end - off} left before the CRC"
                )
        if problem is not None:
            if not salvage:
                raise FlightFormatError(path, problem)
            stop = (off, problem)
            break
        add_start(off)
        add_id(eid)
        off += n
    return np.asarray(starts, dtype=np.int64), np.asarray(ids, dtype=np.int64), stop


def decode_crazyflie_log(path: str | Path, check_crc: bool = True) -> CrazyflieLog:
    """Decode a Crazyflie SD-card log (format in the module docstring).

    Args:
        path: the log file.
        check_crc: verify the trailing CRC-32 (a mismatch is an error). ``False`` salvages a
            damaged file: when the CRC does not match (a bit flipped, or a log cut off by a
            power loss, which writes no CRC), every byte after the header may be a record and
            decoding stops at the first record that cannot be read (an unknown event id, or
            one cut off); what was found and dropped is in ``CrazyflieLog.damage``. Records
            before that point are taken as they are: the format has no per-record check.

    Raises:
        FlightFormatError: one line naming the file and the byte offset / record: bad header,
            unknown version, CRC mismatch, unknown event id, truncated record.
    """
    path = existing_file(path, "Crazyflie SD-card log")
    data = path.read_bytes()
    version, types, first = parse_header(data, path)
    problem = _crc_problem(data)
    if problem and check_crc:
        raise FlightFormatError(path, problem + SALVAGE_HINT)
    starts, ids, stop = _record_starts(data, version, types, first, path, bool(problem))
    damage = None
    if problem:
        at = stop[0] if stop else len(data)
        damage = {
            "crc": problem,
            "stopped_at_byte": at,
            "reason": stop[1] if stop else None,
            "bytes_dropped": len(data) - at,
        }
    buf = np.frombuffer(data, dtype=np.uint8)
    stamp_dtype = STAMP_DTYPES[version][0]
    records: dict[str, np.ndarray] = {}
    for e in types.values():
        payload = e.payload_dtype()
        dtype = np.dtype(
            [("_id", "<u2"), (STAMP, stamp_dtype)] + [(n, payload[n]) for n in payload.names]
        )
        at = starts[ids == e.id]
        raw = (
            buf[at[:, None] + np.arange(dtype.itemsize)]
            if at.size
            else np.zeros((0, dtype.itemsize), np.uint8)
        )
        rec = np.ascontiguousarray(raw).view(dtype).reshape(-1)
        records[e.name] = rec[[STAMP, *payload.names]]
    return CrazyflieLog(
        path=path,
        version=version,
        event_types=types,
        records=records,
        n_records=int(starts.size),
        header_bytes=first,
        damage=damage,
    )


def check_crazyflie_log(path: str | Path) -> str | None:
    """``None`` when ``path`` is a Crazyflie log (its whole header parses and its CRC matches),
    else the reason it is not. Reads only the first byte of a file that lacks the magic."""
    p = Path(path)
    try:
        if not p.is_file():
            return "not a file"
        with p.open("rb") as f:
            if f.read(1) != bytes([MAGIC]):
                return f"byte 0 is not the magic 0x{MAGIC:X}"
        data = p.read_bytes()
        parse_header(data, p)
    except FlightFormatError as e:
        return e.reason
    except OSError as e:
        return f"cannot read ({e})"
    problem = _crc_problem(data)
    return None if problem is None else problem + SALVAGE_HINT


def is_crazyflie_log(path: str | Path) -> bool:
    """True when ``path`` is a Crazyflie SD-card log: magic, version, the whole header and the
    CRC-32 all check (see :func:`check_crazyflie_log`)."""
    return check_crazyflie_log(path) is None


# ----------------------------------------------------------------------------------------------
# Streams
# ----------------------------------------------------------------------------------------------


def _columns(rec: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    return np.column_stack([rec[n].astype(np.float64) for n in names])


def pair_imu(
    t_gyro: np.ndarray, t_acc: np.ndarray, tolerance_s: float = IMU_PAIR_TOLERANCE_S
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest pairing of gyro and accelerometer stamps.

    Returns:
        ``(gyro indices, accelerometer indices)`` of the pairs, in gyro order; a gyro sample whose
        nearest accelerometer sample is farther than ``tolerance_s``, or is nearer to another
        gyro sample, has no pair.
    """
    if t_gyro.size == 0 or t_acc.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.searchsorted(t_acc, t_gyro)
    lo, hi = np.clip(j - 1, 0, t_acc.size - 1), np.clip(j, 0, t_acc.size - 1)
    pick = np.where(np.abs(t_acc[lo] - t_gyro) <= np.abs(t_acc[hi] - t_gyro), lo, hi)
    dist = np.abs(t_acc[pick] - t_gyro)
    gi = np.flatnonzero(dist <= tolerance_s)
    # One gyro per accelerometer sample: the nearest wins.
    order = np.lexsort((dist[gi], pick[gi]))
    gi = gi[order]
    first = np.ones(gi.size, dtype=bool)
    first[1:] = pick[gi][1:] != pick[gi][:-1]
    gi = np.sort(gi[first])
    return gi, pick[gi]


def imu_from_log(cf: CrazyflieLog) -> tuple[ImuSeries, dict[str, Any]]:
    """``estGyroscope`` + ``estAcceleration`` -> IMU in body FLU, SI units, at the gyro times."""
    g = cf.require("estGyroscope", GYRO_FIELDS)
    a = cf.require("estAcceleration", ACCEL_FIELDS)
    tg, ta = cf.time_s("estGyroscope"), cf.time_s("estAcceleration")
    gyro = _columns(g, GYRO_FIELDS) * DEG_TO_RAD
    acc = _columns(a, ACCEL_FIELDS) * FIRMWARE_GRAVITY
    keep_g = increasing_mask(tg)
    keep_a = increasing_mask(ta)
    for event, t, keep in (("estGyroscope", tg, keep_g), ("estAcceleration", ta, keep_a)):
        reset = clock_reset(t, keep)
        if reset is not None:
            i, back = reset
            raise FlightFormatError(
                cf.path,
                f"{event}: the clock goes back {back:.3f} s at record {i} (t={t[i]:.3f} s), "
                "a clock reset: split the log there",
            )
    gi_all, ai_all = np.flatnonzero(keep_g), np.flatnonzero(keep_a)
    gi, ai = pair_imu(tg[gi_all], ta[ai_all])
    gi, ai = gi_all[gi], ai_all[ai]
    finite = np.all(np.isfinite(gyro[gi]), axis=1) & np.all(np.isfinite(acc[ai]), axis=1)
    plausible = imu_plausible(gyro[gi], acc[ai])
    notes: dict[str, Any] = {
        "gyro_samples": int(tg.size),
        "accel_samples": int(ta.size),
        "units": "gyro deg/s -> rad/s; acc g -> m/s^2 x 9.81 (firmware GRAVITY_MAGNITUDE)",
        "time": "gyro stamp; accelerometer paired by nearest stamp within "
        f"{IMU_PAIR_TOLERANCE_S * 1e3:.1f} ms (not interpolated)",
        "skipped_gyro_time_not_increasing": int(np.count_nonzero(~keep_g)),
        "skipped_accel_time_not_increasing": int(np.count_nonzero(~keep_a)),
        "skipped_gyro_without_accel": int(gi_all.size - gi.size),
        "skipped_accel_without_gyro": int(ai_all.size - ai.size),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_implausible": int(np.count_nonzero(finite & ~plausible)),
    }
    if gi.size:
        dt_pair = ta[ai] - tg[gi]
        notes["accel_minus_gyro_stamp_ms"] = {
            "median": float(np.median(dt_pair) * 1e3),
            "max_abs": float(np.max(np.abs(dt_pair)) * 1e3),
        }
    gi, ai = gi[finite & plausible], ai[finite & plausible]
    if gi.size < 2:
        raise FlightFormatError(
            cf.path,
            f"estGyroscope/estAcceleration: {gi.size} usable IMU sample(s) of {tg.size} "
            f"({notes['skipped_gyro_time_not_increasing']} gyro stamps not increasing, "
            f"{notes['skipped_gyro_without_accel']} without an accelerometer sample, "
            f"{notes['skipped_nonfinite']} non-finite, {notes['skipped_implausible']} beyond "
            f"{IMU_MAX_RATE:g} rad/s or {IMU_MAX_ACCEL:g} m/s^2)",
        )
    return ImuSeries(t=tg[gi], body_omega=gyro[gi], body_accel=acc[ai]), notes


def flow_from_log(cf: CrazyflieLog) -> tuple[FlowSeries | None, dict[str, Any]]:
    """``estFlow`` -> integrated flow in fgnav's sensor frame (motion pixels; see module doc)."""
    rec = cf.require("estFlow", FLOW_FIELDS)
    t = cf.time_s("estFlow")
    dx = rec["motion.deltaX"].astype(np.float64)
    dy = rec["motion.deltaY"].astype(np.float64)
    ok = (np.abs(dx) < FLOW_MAX_COUNTS) & (np.abs(dy) < FLOW_MAX_COUNTS)
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    notes: dict[str, Any] = {
        "samples": int(t.size),
        "skipped_implausible": int(np.count_nonzero(~ok)),
        "skipped_time_not_increasing": int(np.count_nonzero(ok & ~keep)),
        "axes": "flow = 0.1 * [motion.deltaY, -motion.deltaX] (firmware model counts [-NX, NY])",
    }
    t = t[keep]
    if t.size == 0:
        return None, notes
    dx, dy = dx[keep], dy[keep]
    flow = FLOW_RESOLUTION * np.column_stack([dy, -dx])
    step = np.diff(t)
    loop = float(np.median(step)) if step.size else 0.01
    dt = np.empty(t.size)
    dt[0] = loop
    after_gap = step > FLOW_GAP_FACTOR * loop
    dt[1:] = np.where(after_gap, loop, step)
    notes.update(
        loop_period_s=loop,
        dt=f"step from the previous sample, or one loop ({loop * 1e3:.2f} ms, the median step) "
        f"after a step over {FLOW_GAP_FACTOR:g} loops and for the first sample",
        dt_one_loop_after_gap=int(np.count_nonzero(after_gap)),
        longest_gap_s=float(step.max()) if step.size else 0.0,
    )
    return FlowSeries(t=t, dt=dt, flow=flow), notes


def range_from_log(cf: CrazyflieLog) -> tuple[RangeSeries | None, dict[str, Any]]:
    """``estTOF`` (mm) -> range [m]; zero readings and readings of 5 m or more left out."""
    rec = cf.require("estTOF", (TOF_FIELD,))
    t = cf.time_s("estTOF")
    r = rec[TOF_FIELD].astype(np.float64) * 1e-3
    zero = r <= 0.0
    finite = np.isfinite(r)
    implausible = finite & (r >= TOF_PLAUSIBLE_MAX_M)
    ok = finite & ~zero & ~implausible
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    notes = {
        "samples": int(t.size),
        "skipped_zero": int(np.count_nonzero(zero)),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_implausible": int(np.count_nonzero(implausible)),
        "skipped_time_not_increasing": int(np.count_nonzero(ok & ~keep)),
        "outside_min_max_kept": int(
            np.count_nonzero(keep & ((r < TOF_RANGE_MIN_M) | (r > TOF_RANGE_MAX_M)))
        ),
    }
    if zero.any():
        notes["zero_at_s"] = [float(x) for x in (t[zero].min(), t[zero].max())]
    if not keep.any():
        return None, notes
    return RangeSeries(t=t[keep], range=r[keep]), notes


def ground_truth_from_log(cf: CrazyflieLog) -> tuple[Trajectory | None, dict[str, Any]]:
    """``estPose`` -> Vicon trajectory (``[w, x, y, z]``); exact repeats left out."""
    rec = cf.require("estPose", POSE_FIELDS)
    t = cf.time_s("estPose")
    vals = _columns(rec, POSE_FIELDS)
    repeat = np.zeros(t.size, dtype=bool)
    if t.size > 1:
        repeat[1:] = np.all(vals[1:] == vals[:-1], axis=1)
    q_xyzw = vals[:, 3:]
    norm = np.linalg.norm(q_xyzw, axis=1)
    finite = np.all(np.isfinite(vals), axis=1)
    bad_norm = finite & (np.abs(norm - 1.0) > 1e-3)
    ok = finite & ~bad_norm & ~repeat
    keep = ok & increasing_mask(np.where(ok, t, -np.inf))
    notes: dict[str, Any] = {
        "samples": int(t.size),
        "skipped_exact_repeat": int(np.count_nonzero(repeat)),
        "skipped_nonfinite": int(np.count_nonzero(~finite)),
        "skipped_quaternion_norm_off": int(np.count_nonzero(bad_norm & ~repeat)),
        "skipped_time_not_increasing": int(np.count_nonzero(ok & ~keep)),
        "time": "stamped on arrival by radio (README: ~2 ms after the IMU); not shifted",
        "source": "estPose locSrv.* (Vicon pose streamed to the vehicle)",
    }
    if not keep.any():
        return None, notes
    q = q_xyzw[keep] / norm[keep, None]
    q_wxyz = np.column_stack([q[:, 3], q[:, :3]])
    p = vals[keep, :3]
    v = velocity_from_positions(t[keep], p, GT_VELOCITY_WINDOW_S, GT_VELOCITY_RATE_HZ)
    notes["velocity"] = (
        f"derived: Savitzky-Golay derivative of the positions ({GT_VELOCITY_WINDOW_S:g} s window "
        f"on a {GT_VELOCITY_RATE_HZ:g} Hz resampling; Vicon positions are quantised to 1 mm)"
    )
    traj = Trajectory(t=t[keep], world_t_body=p, world_q_body_wxyz=q_wxyz, world_v_body=v)
    return traj, notes


def barometer_summary(cf: CrazyflieLog) -> dict[str, Any] | None:
    """Summary of ``estBarometer`` (fgnav has no barometer stream)."""
    if "estBarometer" not in cf.records or len(cf.records["estBarometer"]) == 0:
        return None
    rec = cf.require("estBarometer", (BARO_FIELD,))
    t = cf.time_s("estBarometer")
    asl = rec[BARO_FIELD].astype(np.float64)
    changes = int(np.count_nonzero(np.diff(asl) != 0)) if asl.size > 1 else 0
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    return {
        "samples": int(t.size),
        "value_updates": changes,
        "update_rate_hz": changes / span if span > 0 else 0.0,
        "asl_min_m": float(np.nanmin(asl)),
        "asl_max_m": float(np.nanmax(asl)),
        "note": "baro.asl [m above sea level]; not converted: fgnav has no barometer stream "
        "(decode_crazyflie_log gives the samples)",
    }


def imu_noise_from_still(imu: ImuSeries) -> tuple[ImuNoise | None, dict[str, Any]]:
    """White-noise densities from the still window at the start of the IMU (see module doc);
    ``None`` when there is no still window long enough (at least 4 blocks)."""
    default = ImuNoise()
    rate = imu.rate_hz
    win = max(int(round(STILL_MIN_S * rate)), 2) if rate > 0 else 0
    n_win = len(imu) // win if win else 0
    still_windows = 0
    deg = imu.body_omega / DEG_TO_RAD
    for k in range(n_win):
        if np.all(deg[k * win : (k + 1) * win].std(axis=0) < STILL_GYRO_STD_DEG_S):
            still_windows += 1
        else:
            break
    n = still_windows * win
    block = int(round(NOISE_BLOCK_S * rate)) if rate > 0 else 0
    if still_windows == 0 or block < 2 or n // block < 4:
        return None, {
            "source": f"no still window of {STILL_MIN_S * 1e3:.0f} ms at the start of the log",
        }
    nb = n // block
    t_block = block / rate

    def density(x: np.ndarray) -> float:
        means = x[: nb * block].reshape(nb, block, 3).mean(axis=1)
        return float(np.sqrt(np.mean(means.var(axis=0, ddof=1)) * t_block))

    noise = dataclasses.replace(
        default,
        gyro_noise_density=density(imu.body_omega),
        accel_noise_density=density(imu.body_accel),
    )
    return noise, {
        "source": f"still window at the start of the log: {n / rate * 1e3:.0f} ms ({n} samples), "
        f"std of {nb} block means of {t_block * 1e3:.0f} ms x sqrt(block)",
        "used": "no: calib.imu_noise is CRAZYFLIE_IMU_NOISE (in flight, pooled over the UTIL logs)",
        "blocks": nb,
        "gyro_noise_density": noise.gyro_noise_density,
        "accel_noise_density": noise.accel_noise_density,
    }


# ----------------------------------------------------------------------------------------------
# The reader
# ----------------------------------------------------------------------------------------------


def crazyflie_calibration(imu_noise: ImuNoise = CRAZYFLIE_IMU_NOISE) -> Calibration:
    """The flow deck's calibration (module docstring): ToF and flow sensor under the body centre,
    beam / optical axis along body -z, lever arm :data:`TOF_LEVER_Z`, the firmware's flow scale."""
    lever = np.array([0.0, 0.0, TOF_LEVER_Z])
    return Calibration(
        body_T_range=make_pose(DOWNWARD_RANGE[:3, :3], lever),
        body_T_flow=make_pose(DOWNWARD_FLOW[:3, :3], lever),
        flow_pixels_per_rad=FLOW_PIXELS_PER_RAD,
        flow_rate_gain=FLOW_RATE_GAIN,
        range_min=TOF_RANGE_MIN_M,
        range_max=TOF_RANGE_MAX_M,
        imu_noise=imu_noise,
    )


def read_crazyflie(path: str | Path, check_crc: bool = True) -> Flight:
    """Read a Crazyflie SD-card log into a :class:`Flight` (module docstring).

    Returns:
        The flight, checked: ``imu`` (always), ``flow``, ``range``, ``ground_truth`` when the log
        has them, ``calib`` from :func:`crazyflie_calibration` with the IMU noise of the still
        start, and ``meta`` with per-stream notes (counts of what was left out, by reason),
        event counts and the barometer summary.

    Raises:
        FlightFormatError: a bad file (see :func:`decode_crazyflie_log`) or no IMU records.
    """
    cf = decode_crazyflie_log(path, check_crc=check_crc)
    counts = cf.counts()
    meta: dict[str, Any] = {
        "format": "crazyflie-usd-log",
        "crazyflie_version": cf.version,
        "crazyflie_events": counts,
        "records": cf.n_records,
        "frames": "body FLU (Crazyflie body x forward, y left, z up); world = Vicon frame, z up",
        "time": "seconds on the vehicle's clock since boot (log stamps "
        + ("us" if cf.version == 2 else "ms")
        + ")",
        "notes": [],
    }
    if cf.damage is not None:
        d = cf.damage
        meta["damage"] = dict(d)
        msg = (
            f"damaged log salvaged ({d['crc']}): {cf.n_records} records read, "
            f"{d['bytes_dropped']} bytes from byte {d['stopped_at_byte']} dropped"
            + (f" ({d['reason']})" if d["reason"] else "")
            + "; the records read have no check of their own"
        )
        meta["notes"].append(msg)
        log.warning("%s: %s", cf.path, msg)
    for name in IMU_EVENTS:
        if counts.get(name, 0) == 0:
            raise FlightFormatError(
                cf.path,
                f"no {name} records: the log has no IMU data to read (events: "
                + ", ".join(f"{k} {v}" for k, v in counts.items())
                + ")",
            )
    imu, meta["imu"] = imu_from_log(cf)
    if len(imu) == 0:
        raise FlightFormatError(cf.path, "no gyro sample has an accelerometer sample beside it")
    _, meta["imu_noise"] = imu_noise_from_still(imu)

    streams: dict[str, Any] = {}
    for key, event, fn in (
        ("flow", "estFlow", flow_from_log),
        ("range", "estTOF", range_from_log),
        ("ground_truth", "estPose", ground_truth_from_log),
    ):
        if counts.get(event, 0) == 0:
            meta["notes"].append(f"no {event} records: flight.{key} is empty")
            continue
        series, meta[key] = fn(cf)
        if series is not None:
            streams[key] = series
    baro = barometer_summary(cf)
    if baro is not None:
        meta["barometer"] = baro
    unread = [n for n, c in counts.items() if c and n not in READ_EVENTS]
    if unread:
        meta["notes"].append("not read: " + ", ".join(f"{n} ({counts[n]} records)" for n in unread))
    if "flow" in meta:
        meta["notes"].append(
            f"flow dt: one loop ({meta['flow']['loop_period_s'] * 1e3:.2f} ms) for "
            f"{meta['flow']['dt_one_loop_after_gap']} sample(s) after a gap (not logged: the "
            "sensor is read every loop and logged only with valid motion)"
        )
    flight = Flight(
        name=cf.path.name,
        source=str(cf.path),
        imu=imu,
        calib=crazyflie_calibration(),
        meta=meta,
        **streams,
    )
    log.info(
        "read Crazyflie log %s: %d records, %s", cf.path, cf.n_records, ", ".join(flight.streams())
    )
    return flight.check()
