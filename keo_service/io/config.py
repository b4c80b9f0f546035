"""The TOML config (docs/design.md §6), read with tomllib and validated with msgspec.

Every key is optional except `robot.urdf`; unknown keys are errors. Errors name the key.
Relative paths are resolved against the config file's folder.
"""

from __future__ import annotations

import difflib
import re
import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import msgspec
import tomli_w

from keo_service.core.compensation import DEFAULT_MAX_AGE_S, CompensationLimits
from keo_service.core.errors import ConfigError
from keo_service.core.model_corrections import MAP_TAPER_RAD
from keo_service.core.settings import EstimatorSettings
from keo_service.io.protocols import PROTOCOLS
from keo_service.io.protocols import names as protocol_names

# the estimator's defaults are the config's defaults: one place for each value
_DEFAULTS = EstimatorSettings()

Finite = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]
Vec3 = Annotated[list[Finite], msgspec.Meta(min_length=3, max_length=3)]
Gain = Annotated[float, msgspec.Meta(gt=0.0, le=1e4)]
Port = Annotated[int, msgspec.Meta(ge=1, le=65535)]
CellName = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_\-]+$")]


class _Section(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    pass


# the defaults by protocol, from the protocol table (io.protocols): the controller's port when
# `robot.port` is not given (ros2 has none: it comes over the bus), and the clock domain a
# protocol's stamps are on when `clock` is not given
DEFAULT_ROBOT_PORTS = {p.name: p.port for p in PROTOCOLS if p.section == "robot"}
DEFAULT_ROBOT_CLOCKS = {p.name: p.clock for p in PROTOCOLS if p.section == "robot"}
DEFAULT_TRACKER_CLOCKS = {p.name: p.clock for p in PROTOCOLS if p.section == "tracker"}
if TYPE_CHECKING:
    RobotProtocol = str
    TrackerProtocol = str
else:  # the values the table has: msgspec refuses others, naming the key and the choices
    RobotProtocol = Literal[protocol_names("robot")]
    TrackerProtocol = Literal[protocol_names("tracker")]
ClockDomain = Literal["shared", "device", "receipt"]
RosTopic = Annotated[
    str, msgspec.Meta(pattern=r"^/[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$")
]


class RobotConfig(_Section):
    urdf: str
    base_frame: str = "base_link"
    flange_frame: str = "tool0"
    # "motoros": ROS-Industrial simple message (MotoROS); "rtde": Universal Robots RTDE;
    # "ros2": sensor_msgs/msg/JointState over rmw_zenoh (any ROS 2 driver)
    # "kuka_rsi": KUKA RobotSensorInterface (keo is the UDP server); "abb_egm": ABB EGM
    protocol: RobotProtocol = "motoros"
    # what the stamps are: "shared" (already on the cell's common clock), "device" (the
    # controller's own clock, mapped onto the host's), "receipt" (none: stamped on arrival);
    # not given: the protocol's default (DEFAULT_ROBOT_CLOCKS)
    clock: ClockDomain | None = None
    # where live corrections go: "none", "rtde_registers" (six RTDE input double registers
    # from correction_register on), "kuka_rsi" (RKorr in the RSI reply), "abb_egm"
    correction: Literal["none", "rtde_registers", "kuka_rsi", "abb_egm"] = "none"
    correction_register: Annotated[int, msgspec.Meta(ge=0, le=42)] = 24
    host: str = "127.0.0.1"
    # 0: the protocol's default, 50241 for motoros, 30004 for rtde (ros2 uses none)
    port: Annotated[int, msgspec.Meta(ge=0, le=65535)] = 0
    byte_order: Literal["little", "big"] = "little"
    # rtde: the output rate asked of the controller (500 Hz on e-Series, 125 Hz on CB3)
    frequency_hz: Annotated[float, msgspec.Meta(gt=0.0, le=500.0)] = 500.0
    # ros2: joints picked by name into the URDF's order
    joint_states_topic: RosTopic = "/joint_states"
    # a connected controller that sends nothing for this long is reported silent (log, status)
    silent_after_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] = 2.0

    def __post_init__(self) -> None:
        if self.port == 0:
            self.port = DEFAULT_ROBOT_PORTS.get(self.protocol, 0)
        if self.clock is None:
            self.clock = DEFAULT_ROBOT_CLOCKS[self.protocol]

    @property
    def endpoint_port(self) -> int:
        """The controller's port (the protocol's default when the config gives none)."""
        return self.port


class ToolConfig(_Section):
    xyz: Vec3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy: Vec3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])


class TrackerConfig(_Section):
    xyz: Vec3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    rpy: Vec3 = msgspec.field(default_factory=lambda: [0.0, 0.0, 0.0])
    # the tracker's probe (or reflector) in the flange frame (m; rad, URDF rpy): a measurement
    # frame, identified by keo analyze; [tool] stays the user's TCP, the frame compensation
    # targets refer to. Not given: the probe is at [tool] (a config whose tool is the probe)
    probe_xyz: Vec3 | None = None
    probe_rpy: Vec3 | None = None
    host: str = "127.0.0.1"
    port: Port = 5005
    # "line": keo's line protocol over TCP; "ros2": geometry_msgs/msg/PoseStamped (or
    # PointStamped for a single reflector) over rmw_zenoh, metres
    protocol: TrackerProtocol = "line"
    pose_topic: RosTopic = "/lasertracker/pose"
    # the stamps' clock domain (see RobotConfig.clock); not given: DEFAULT_TRACKER_CLOCKS
    clock: ClockDomain | None = None
    # standard uncertainty per coordinate: a constant part and one proportional to the
    # distance from the tracker (a datasheet's "15 um + 6 um/m")
    uncertainty_um: Annotated[float, msgspec.Meta(ge=0.0, le=1e5)] = 15.0
    uncertainty_um_per_m: Annotated[float, msgspec.Meta(ge=0.0, le=1e4)] = 6.0
    # a connected tracker that sends nothing for this long is reported silent (log, status)
    silent_after_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] = 2.0

    def __post_init__(self) -> None:
        if self.clock is None:
            self.clock = DEFAULT_TRACKER_CLOCKS[self.protocol]


class Ros2Config(_Section):
    """rmw_zenoh's wire format on keo's own Zenoh sessions (docs/design.md §6)."""

    enabled: bool = False
    domain_id: Annotated[int, msgspec.Meta(ge=0, le=232)] = 0
    distro: Literal["humble", "iron", "jazzy", "kilted", "rolling"] = "jazzy"
    publish_tf: bool = False


# the observer's channels: the error's three translations and three rotations
GAIN_CHANNELS = ("px", "py", "pz", "rx", "ry", "rz")


class ObserverConfig(_Section):
    # one gain (1/s) per channel; a single number in the file is the same gain on every channel
    gain: Annotated[list[Gain], msgspec.Meta(min_length=6, max_length=6)] = msgspec.field(
        default_factory=lambda: list(_DEFAULTS.gains)
    )
    # A sample that follows a gap longer than this updates as if it came after max_dt_s,
    # so one measurement after a beam break cannot pull the estimate all the way.
    max_dt_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = _DEFAULTS.max_dt_s


DEFAULT_DELAY_SE_S = 0.0005  # a delay configured without its uncertainty (docs/timing-delay.md)


class TimingConfig(_Section):
    delay_s: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.0
    # the standard uncertainty of delay_s (keo calibrate-delay writes it): the online fit
    # takes delay_s as a prior with it; delay_s = 0 (the default) means "not known" whatever
    # this says (found from the motion, estimates flagged until it settles)
    delay_se_s: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = DEFAULT_DELAY_SE_S
    drift_ppm: Annotated[float, msgspec.Meta(ge=-10000.0, le=10000.0)] = 0.0
    # stream time (s) at which delay_s holds when drift_ppm is not zero
    drift_ref_s: float = 0.0
    alignment: Literal["interpolate", "latest"] = "interpolate"
    sample_rate_hz: Annotated[float, msgspec.Meta(gt=0.0, le=10000.0)] = _DEFAULTS.sample_rate_hz
    # follow the delay online while the tool moves, starting from delay_s (docs/design.md §6)
    track_delay: bool = True
    # Encoder samples kept for alignment, in seconds of stream time.
    buffer_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = _DEFAULTS.buffer_s
    # Two encoder samples further apart than this are not interpolated between.
    max_gap_s: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = _DEFAULTS.max_gap_s
    # A tracker sample waits at most this long (stream time) for encoder data to cover it.
    stale_after_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = _DEFAULTS.stale_after_s
    # a "shared"-clock stamp older than this at receipt (or ahead of it) is counted and flagged
    max_stamp_age_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = 0.5
    # where adapters keep their device-clock mappings, so that a restarted adapter goes on
    # on the same line ("" = not kept; relative to the config file)
    clock_state_dir: str = ""


class CompensationConfig(_Section):
    """Limits on live corrections (keo/<cell>/correction): larger or faster ones are clamped
    and counted."""

    max_mm: Annotated[float, msgspec.Meta(gt=0.0, le=1e3)] = 5.0
    max_mrad: Annotated[float, msgspec.Meta(gt=0.0, le=1e3)] = 5.0
    max_rate_mm_s: Annotated[float, msgspec.Meta(gt=0.0, le=1e4)] = 50.0
    # the correction's own cycle (Hz): validity checked, a correction renewed or invalidated
    # at least this often; 0: the observer's period (the estimates' mean step)
    rate_hz: Annotated[float, msgspec.Meta(ge=0.0, le=1000.0)] = 0.0
    # valid only while the newest encoder sample, the newest tracker pose and the newest
    # estimate arrived within this (host time); the controller interfaces' 0.1 s age limit
    stale_after_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = 0.1
    # a received correction older than this is not applied by any controller interface (the
    # RTDE registers, KUKA RSI, ABB EGM): they send zero instead
    max_age_s: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = DEFAULT_MAX_AGE_S

    def limits(self) -> CompensationLimits:
        """These limits in SI units: what the service and every controller output apply."""
        return CompensationLimits.from_config_values(
            self.max_mm, self.max_mrad, self.max_rate_mm_s, self.max_age_s
        )


class RegionBandConfig(_Section):
    """The box (base frame, m) the calibration poses' tool swept in one orientation band."""

    band: Literal["down", "side", "up"]
    poses: Annotated[int, msgspec.Meta(ge=1)]
    lower: Vec3
    upper: Vec3


class BusConfig(_Section):
    mode: Literal["peer", "client"] = "peer"
    listen: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = msgspec.field(default_factory=list)
    multicast_scouting: bool = False
    # TLS (endpoints "tls/host:port"): the CA that signed the other side's certificate, and
    # this node's own certificate and key; tls_mtls makes both sides prove who they are
    tls_root_ca: str = ""
    tls_certificate: str = ""
    tls_private_key: str = ""
    tls_mtls: bool = False
    # per-key rights on the bus (needs tls_mtls): each session and `keo router` enforce them
    access_control: bool = False
    # mTLS certificate common name -> role
    roles: dict[str, Literal["encoder", "tracker", "service", "client", "operator", "router"]] = (
        msgspec.field(default_factory=dict)
    )


class ModelConfig(_Section):
    """Effects `keo analyze` identified (written into model.toml). Applied live: joint
    offsets, geometry (placement), compliance, cyclic. Backlash, temperature and time drift
    are reported by the analysis but need inputs the live stream does not carry."""

    effects: list[str] = msgspec.field(default_factory=list)
    joint_offsets: list[float] = msgspec.field(default_factory=list)  # rad, per joint
    compliance: list[float] = msgspec.field(default_factory=list)  # rad/(N m), per joint
    backlash: list[float] = msgspec.field(default_factory=list)  # rad, per joint
    cyclic: list[float] = msgspec.field(default_factory=list)  # per joint: a1, b1, a2, b2 (rad)
    placement: list[float] = msgspec.field(default_factory=list)  # per joint: 6-vector (m, rad)
    # joint-angle error maps: per joint the knots (rad, increasing) and the angle error there
    # (rad); an empty list: no map for that joint
    map_knots: list[list[float]] = msgspec.field(default_factory=list)
    map_values: list[list[float]] = msgspec.field(default_factory=list)
    # rad: each map fades to zero over this distance outside its knots (keo analyze chooses
    # it; files written before that get the distance they were made with)
    map_taper_rad: float = MAP_TAPER_RAD
    # couplings across joints (keo analyze): per coupling [j, k] (joint j's angle error moves
    # with joint k's angle, 0-based), the slope (rad/rad, about the knots' centre), and a map
    # of joint k's angle (knots rad, increasing; values rad)
    coupling_joints: list[list[int]] = msgspec.field(default_factory=list)
    coupling_slopes: list[float] = msgspec.field(default_factory=list)
    coupling_knots: list[list[float]] = msgspec.field(default_factory=list)
    coupling_values: list[list[float]] = msgspec.field(default_factory=list)
    # periodic joint errors (keo analyze's joint_ripple): per term the joint (0-based), the
    # period (rad of that joint's angle) and the sine and cosine amplitudes (rad)
    ripple_joints: list[int] = msgspec.field(default_factory=list)
    ripple_periods_rad: list[float] = msgspec.field(default_factory=list)
    ripple_sin: list[float] = msgspec.field(default_factory=list)
    ripple_cos: list[float] = msgspec.field(default_factory=list)
    # the model's stated accuracy off its calibrated joint ranges (fit.accuracy: held-out
    # position RMS on extrapolation bands, mm); inside them it is accuracy_mm below
    accuracy_outside_mm: float = 0.0
    # and what a session other than the calibration's adds to it in quadrature (mm; from
    # leave-one-session-out, or the bands' default with one session), and how it was found
    accuracy_session_mm: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    accuracy_session_source: str = ""
    temperature_m_per_c: list[float] = msgspec.field(default_factory=list)
    temperature_ref_c: float = 0.0
    time_drift_m_per_s: list[float] = msgspec.field(default_factory=list)
    time_ref_s: float = 0.0
    # the model in the nominal robot's frames (keo analyze): its tool pose is
    # base * chain(q) * flange * tool, base and flange the rigid motions the tracker
    # registration and the probe mount cannot tell from the arm (m; rad, URDF rpy)
    base_xyz: list[float] = msgspec.field(default_factory=list)
    base_rpy: list[float] = msgspec.field(default_factory=list)
    flange_xyz: list[float] = msgspec.field(default_factory=list)
    flange_rpy: list[float] = msgspec.field(default_factory=list)
    # what pinned the flange: "probe" (the config's stated probe mount, close to the identified
    # one, taken as true) or "arm" (the arm closest to the nominal robot); "" not pinned
    flange_by: Literal["", "probe", "arm"] = ""
    # where the calibration poses went: each joint's range (rad) and, per tool orientation
    # band, the box of the tool's positions in the base frame
    calibrated_q_min: list[float] = msgspec.field(default_factory=list)
    calibrated_q_max: list[float] = msgspec.field(default_factory=list)
    calibrated_region: list[RegionBandConfig] = msgspec.field(default_factory=list)
    # the model's held-out accuracy (position mm, orientation mrad RMS): the predicted
    # accuracy `keo compensate` gives each target inside the calibrated region
    accuracy_mm: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    accuracy_mrad: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0


class Config(_Section):
    """A validated config file, one attribute per TOML section; docs/config.md lists every
    key with its type, default and unit. Units are SI (m, rad, s, Hz) except where a key's
    name says otherwise (`accuracy_mm`). `load_config` makes one; absent keys hold their
    defaults.

    Attributes:
        robot: [robot]: the URDF, the base and flange frames, the controller's protocol and
            address.
        cell: the cell's name: every key expression on the bus is keo/<cell>/...
        tool: [tool]: the nominal tool frame (TCP) in the flange frame (m, rad).
        tracker: [tracker]: the tracker's frame in the robot base frame (m, rad), the probe
            and the tracker's stream.
        observer: [observer]: the gains (1/s) and the longest step (s).
        timing: [timing]: the delay (s) and its se, alignment, rates (Hz) and buffers (s).
        bus: [bus]: where `keo run` listens and the other processes connect (Zenoh).
        model: [model]: the effects `keo analyze` identified (model.toml).
        ros2: [ros2]: rmw_zenoh's wire format on keo's own Zenoh sessions.
        compensation: [compensation]: limits on live corrections (mm, mrad, mm/s, as the
            keys name them), their rate (Hz) and ages (s).
        source: the file it was read from (not a TOML key).
    """

    robot: RobotConfig
    cell: CellName = "cell1"
    tool: ToolConfig = msgspec.field(default_factory=ToolConfig)
    tracker: TrackerConfig = msgspec.field(default_factory=TrackerConfig)
    observer: ObserverConfig = msgspec.field(default_factory=ObserverConfig)
    timing: TimingConfig = msgspec.field(default_factory=TimingConfig)
    bus: BusConfig = msgspec.field(default_factory=BusConfig)
    model: ModelConfig = msgspec.field(default_factory=ModelConfig)
    ros2: Ros2Config = msgspec.field(default_factory=Ros2Config)
    compensation: CompensationConfig = msgspec.field(default_factory=CompensationConfig)
    source: str = ""

    @property
    def urdf_path(self) -> Path:
        """`robot.urdf` as a path (made absolute against the config's folder on loading)."""
        return Path(self.robot.urdf)

    def bus_endpoints(self) -> list[str]:
        """Endpoints a client process (adapter, echo, record) connects to."""
        return list(self.bus.connect or self.bus.listen)


_PATH_RE = re.compile(r" - at `\$\.?(?P<path>[^`]*)`$")
_UNKNOWN_RE = re.compile(r"Object contains unknown field `(?P<field>[^`]+)`")
_MISSING_RE = re.compile(r"Object missing required field `(?P<field>[^`]+)`")


def known_keys(path: str) -> list[str]:
    """The keys a section of the config accepts ("" for the top level, "robot", "bus", ...)."""
    kind: object = Config
    for part in path.split(".") if path else []:
        fields = {f.name: f.type for f in msgspec.structs.fields(kind)}  # type: ignore[arg-type]
        kind = fields.get(part)
        if not (isinstance(kind, type) and issubclass(kind, msgspec.Struct)):
            return []
    return [f.name for f in msgspec.structs.fields(kind) if f.name != "source"]  # type: ignore[arg-type]


def _did_you_mean(path: str, field: str) -> str:
    close = difflib.get_close_matches(field, known_keys(path), n=1, cutoff=0.6)
    return f"unknown key; did you mean '{close[0]}'?" if close else "unknown key"


def _explain(exc: msgspec.ValidationError, source: str) -> ConfigError:
    text = str(exc)
    match = _PATH_RE.search(text)
    path = match.group("path") if match else ""
    what = text[: match.start()] if match else text
    m = _UNKNOWN_RE.search(what)
    if m:
        key = f"{path}.{m.group('field')}" if path else m.group("field")
        return ConfigError(source, key, _did_you_mean(path, m.group("field")))
    m = _MISSING_RE.search(what)
    if m:
        key = f"{path}.{m.group('field')}" if path else m.group("field")
        return ConfigError(source, key, "required key is missing")
    return ConfigError(source, path or "(top level)", f"{what}")


def _expand_gain(data: dict[str, object], source: str) -> dict[str, object]:
    """`observer.gain` as one number: the same gain on every channel. A list must give one
    gain per channel; say why when its length is wrong."""
    observer = data.get("observer")
    if not isinstance(observer, dict) or "gain" not in observer:
        return data
    gain = observer["gain"]
    n = len(GAIN_CHANNELS)
    if isinstance(gain, int | float) and not isinstance(gain, bool):
        return {**data, "observer": {**observer, "gain": [gain] * n}}
    if isinstance(gain, list) and len(gain) != n:
        raise ConfigError(
            source,
            "observer.gain",
            f"{len(gain)} values; give one number (the same gain on every channel) or a list "
            f"of length {n}, one gain (1/s) per channel {', '.join(GAIN_CHANNELS)}: the "
            "observer follows the error's three translations and three rotations separately",
        )
    return data


# complexity (C901, PLR0912): one cross-key check per rule of docs/design.md §6
def parse_config(  # noqa: C901, PLR0912
    data: dict[str, object], source: str = "<config>", base_dir: Path | None = None
) -> Config:
    """Validate a parsed TOML document; resolve relative paths against `base_dir`."""
    if "source" in data:
        raise ConfigError(source, "source", "unknown key")
    data = _expand_gain(data, source)
    try:
        config = msgspec.convert(data, Config)
    except msgspec.ValidationError as exc:
        raise _explain(exc, source) from None
    urdf = Path(config.robot.urdf)
    if not urdf.is_absolute() and base_dir is not None:
        urdf = (base_dir / urdf).resolve()
    if not urdf.is_file():
        raise ConfigError(source, "robot.urdf", f"file not found: {urdf}")
    robot = msgspec.structs.replace(config.robot, urdf=str(urdf))
    state_dir = config.timing.clock_state_dir
    if state_dir and not Path(state_dir).is_absolute() and base_dir is not None:
        timing = msgspec.structs.replace(
            config.timing, clock_state_dir=str((base_dir / state_dir).resolve())
        )
        config = msgspec.structs.replace(config, timing=timing)
    bus = config.bus
    tls_paths = {}
    for key in ("tls_root_ca", "tls_certificate", "tls_private_key"):
        value = getattr(bus, key)
        if value:
            path = Path(value)
            if not path.is_absolute() and base_dir is not None:
                path = (base_dir / path).resolve()
            if not path.is_file():
                raise ConfigError(source, f"bus.{key}", f"file not found: {path}")
            tls_paths[key] = str(path)
    uses_tls = any(e.startswith("tls/") for e in bus.listen + bus.connect)
    if uses_tls and not bus.tls_root_ca:
        raise ConfigError(source, "bus.tls_root_ca", "tls/ endpoints need the CA certificate")
    if bus.tls_mtls and not (bus.tls_certificate and bus.tls_private_key):
        raise ConfigError(
            source, "bus.tls_mtls", "mutual TLS needs bus.tls_certificate and bus.tls_private_key"
        )
    if bus.access_control and not bus.tls_mtls:
        raise ConfigError(
            source,
            "bus.access_control",
            "access control names identities by their certificates: it needs bus.tls_mtls = true",
        )
    plain = [e for e in bus.listen + bus.connect if not e.startswith("tls/")]
    if bus.access_control and plain:
        key = "bus.listen" if plain[0] in bus.listen else "bus.connect"
        raise ConfigError(
            source,
            key,
            f"{plain[0]}: with access control every endpoint is tls/ (no identity else)",
        )
    if bus.access_control and not bus.roles:
        raise ConfigError(
            source, "bus.roles", "access control with no roles would deny every identity"
        )
    bus = msgspec.structs.replace(bus, **tls_paths)
    _check_clocks(config, source)
    return msgspec.structs.replace(config, robot=robot, bus=bus, source=source)


# protocols whose stamps can only be taken on receipt: MotoROS leaves its time at 0
RECEIPT_ONLY_PROTOCOLS = frozenset({"motoros"})


def _check_clocks(config: Config, source: str) -> None:
    """A clock domain the protocol cannot give is a config error naming the key."""
    robot = config.robot
    if robot.protocol in RECEIPT_ONLY_PROTOCOLS and robot.clock != "receipt":
        raise ConfigError(
            source,
            "robot.clock",
            f'"{robot.clock}" needs time stamps from the controller, and {robot.protocol} '
            'sends none: only "receipt" works (or leave the key out)',
        )


def load_config(path: str | Path) -> Config:
    """Read and validate a config file (TOML, docs/config.md).

    Args:
        path: the config file; relative paths in it are relative to its folder.

    Returns:
        The validated `Config` (SI units: m, rad, s, Hz), every absent key at its default.

    Raises:
        ConfigError: the file cannot be read, is not TOML, or a key is unknown, of the wrong
            type or out of range (the message names the key, with "did you mean").
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), "(file)", f"cannot read config: {exc.strerror}") from None
    except UnicodeDecodeError as exc:  # found fuzzing: it escaped the CLI's exit code 2
        line = path.read_bytes()[: exc.start].count(b"\n") + 1
        raise ConfigError(str(path), "(file)", f"line {line} is not UTF-8 text") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), "(syntax)", f"not valid TOML: {exc}") from None
    return parse_config(data, source=str(path), base_dir=path.parent)


def config_to_toml(config: Config) -> str:
    """Write a config back as TOML (used for model.toml); paths stay absolute. `tomli-w`
    escapes strings and formats floats so that `load_config` reads back the same values."""
    doc: dict[str, object] = {"cell": config.cell}
    for name, section in msgspec.to_builtins(config).items():
        if isinstance(section, dict):  # TOML has no null: an unset optional key is left out
            doc[name] = {k: v for k, v in section.items() if v is not None}
    return tomli_w.dumps(doc)
