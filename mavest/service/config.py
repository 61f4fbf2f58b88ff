"""The service's settings: which IMU stream to follow, what to send back, as whom.

A configuration file has four tables: ``[estimator]`` (the filter,
:class:`~mavest.estimator.EstimatorConfig`), ``[input]``, ``[output]`` and
``[signing]`` (this module). Every table and every key is optional; unknown
keys are an error naming the known ones. Command-line options override the file.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mavest.estimator.config import (
    ConfigError,
    EstimatorConfig,
    check_types,
    read_toml,
    require_number,
    require_table,
)
from mavest.mavlink.messages import IMU_MESSAGES
from mavest.mavlink.signing import (
    KEY_ENVIRONMENT_VARIABLE,
    Signing,
    key_from_file,
    key_from_text,
)

MAV_COMP_ID_ONBOARD_COMPUTER = 191
GROUND_STATION_SYSTEM = 255
ACCELERATION_AIDING = ("auto", "gps", "airspeed", "off")


@dataclass(frozen=True)
class InputConfig:
    """Which messages become estimates."""

    # "auto": per vehicle, the best IMU message it sends (HIGHRES_IMU, then RAW_IMU,
    # SCALED_IMU, SCALED_IMU2, SCALED_IMU3); or one message name; or "all" (an
    # estimator for every IMU stream; ATTITUDE is sent for the best one only).
    imu: str = "auto"
    imu_instance: int = -1  # sensor instance (RAW_IMU/HIGHRES_IMU id); -1: the lowest seen
    system: int = 0  # the vehicle's system id; 0: every vehicle heard
    # Systems whose IMU messages are never estimated (ground stations, radios).
    ignore_systems: tuple[int, ...] = (GROUND_STATION_SYSTEM,)
    # Ask the flight controller for the IMU message at this rate (Hz) on a live link
    # (MAV_CMD_SET_MESSAGE_INTERVAL); 0: leave its rate alone.
    request_rate: float = 0.0
    # Remove the vehicle's own acceleration from the accelerometer (mavest.service.aiding):
    # "gps": from GLOBAL_POSITION_INT velocity while GPS_RAW_INT has a 3-D fix and the
    # magnetometer gives heading; "airspeed": the centripetal term ω × V from VFR_HUD
    # (any vehicle); "auto": GPS when it can, else airspeed on fixed wings (HEARTBEAT
    # type); "off".
    acceleration_aiding: str = "auto"
    # Seconds after a stream's first sample before replay accuracy is scored (convergence).
    settle_time: float = 10.0

    def __post_init__(self) -> None:
        choices = ("auto", "all", *IMU_MESSAGES)
        _require(self.imu in choices, f"input.imu must be one of {', '.join(choices)}")
        _require(-1 <= self.imu_instance <= 255, "input.imu_instance must be -1 or 0–255")
        _require(0 <= self.system <= 255, "input.system must be 0–255")
        _require(all(0 < s <= 255 for s in self.ignore_systems), "ignore_systems: ids 1–255")
        _require(
            math.isfinite(self.request_rate) and 0.0 <= self.request_rate <= 4000.0,
            "input.request_rate must be 0–4000 Hz",
        )
        require_number("input.settle_time", self.settle_time, zero=True)
        _require(
            self.acceleration_aiding in ACCELERATION_AIDING,
            f"input.acceleration_aiding must be one of {', '.join(ACCELERATION_AIDING)}",
        )


@dataclass(frozen=True)
class OutputConfig:
    """What mavest sends, and as whom."""

    # mavest's own ids: system 0 takes the vehicle's system id (a companion computer
    # on that vehicle); component 191 is MAV_COMP_ID_ONBOARD_COMPUTER.
    system_id: int = 0
    component_id: int = MAV_COMP_ID_ONBOARD_COMPUTER
    attitude_rate: float = 0.0  # Hz; 0: one ATTITUDE per IMU sample
    attitude_quaternion: bool = True  # also send ATTITUDE_QUATERNION
    heartbeat_rate: float = 1.0  # Hz; 0: none
    # Send estimates and HEARTBEAT back on the link listened on (live); false: only to
    # the --out links (a ground station on the vehicle's link then never sees them).
    reply_on_input: bool = True

    def __post_init__(self) -> None:
        _require(0 <= self.system_id <= 255, "output.system_id must be 0–255 (0: the vehicle's)")
        _require(1 <= self.component_id <= 255, "output.component_id must be 1–255")
        require_number("output.attitude_rate", self.attitude_rate, zero=True)
        require_number("output.heartbeat_rate", self.heartbeat_rate, zero=True)


@dataclass(frozen=True)
class SigningConfig:
    """MAVLink 2 signing on a live link (``mavest run``); the key itself is never stored here.

    The key comes from ``--signing-key FILE``, else the environment variable
    MAVEST_SIGNING_KEY (hex or passphrase), else ``key_file``; with none of them,
    nothing is signed or verified. Formats: :mod:`mavest.mavlink.signing`.
    """

    # File holding the key: 32 raw bytes, 64 hex digits, or a passphrase (key = its
    # SHA-256, as MAVProxy's `signing setup`). Relative to the configuration file.
    key_file: str = ""
    sign_outgoing: bool = True  # sign what mavest sends (when there is a key)
    # Drop unsigned input (needs a key). Signed input is verified whenever there is a key.
    require_signed: bool = False

    def __post_init__(self) -> None:
        _require(isinstance(self.key_file, str), "signing.key_file must be a path (a string)")
        _require(isinstance(self.sign_outgoing, bool), "signing.sign_outgoing must be true/false")
        _require(isinstance(self.require_signed, bool), "signing.require_signed must be true/false")

    def resolve(
        self, environ: Mapping[str, str], key_file: str | Path | None = None
    ) -> Signing | None:
        """The key and policy to run with, or None (no signing) when no key is given.

        ``key_file`` (the command line's) comes first, then the environment variable
        (an empty one counts as unset), then this table's ``key_file``. A
        :class:`~mavest.mavlink.signing.SigningKeyError` says what is wrong with a key.
        """
        if key_file is None and environ.get(KEY_ENVIRONMENT_VARIABLE):
            source = KEY_ENVIRONMENT_VARIABLE
            key, kind = key_from_text(environ[KEY_ENVIRONMENT_VARIABLE], source)
        else:
            path = key_file if key_file is not None else self.key_file
            if not path:
                _require(
                    not self.require_signed,
                    "require_signed needs a signing key: --signing-key FILE, "
                    f"{KEY_ENVIRONMENT_VARIABLE} or [signing] key_file",
                )
                return None
            source = str(path)
            key, kind = key_from_file(path)
        return Signing(key, self.sign_outgoing, self.require_signed, source, kind)


@dataclass(frozen=True)
class ServiceConfig:
    """Everything a configuration file sets."""

    estimator: EstimatorConfig = dataclasses.field(default_factory=EstimatorConfig)
    input: InputConfig = dataclasses.field(default_factory=InputConfig)
    output: OutputConfig = dataclasses.field(default_factory=OutputConfig)
    signing: SigningConfig = dataclasses.field(default_factory=SigningConfig)

    @classmethod
    def from_mapping(cls, document: dict[str, Any]) -> ServiceConfig:
        unknown = sorted(set(document) - {"estimator", "input", "output", "signing"})
        _require(
            not unknown,
            f"unknown table(s) {', '.join(unknown)}: use estimator, input, output, signing",
        )
        return cls(
            EstimatorConfig.from_mapping(document.get("estimator", {})),
            _table(InputConfig, document.get("input", {}), "input"),
            _table(OutputConfig, document.get("output", {}), "output"),
            _table(SigningConfig, document.get("signing", {}), "signing"),
        )

    @classmethod
    def from_toml(cls, path: str | Path) -> ServiceConfig:
        document = read_toml(path)
        try:
            config = cls.from_mapping(document)
        except ConfigError as error:
            raise ConfigError(f"{path}: {error}") from None
        key_file = config.signing.key_file
        if key_file and not Path(key_file).expanduser().is_absolute():
            # a key next to the configuration works wherever mavest is started from
            key_file = str(Path(path).parent / key_file)
            config = config.replace(signing={"key_file": key_file})
        return config

    def replace(self, **changes: dict[str, Any]) -> ServiceConfig:
        """A copy with some keys of some tables changed, e.g. ``output={"system_id": 5}``."""
        tables = {}
        for table, values in changes.items():
            tables[table] = dataclasses.replace(getattr(self, table), **values)
        return dataclasses.replace(self, **tables)


def _table(cls: type, values: dict[str, Any], name: str) -> Any:
    require_table(values, name)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    _require(
        not unknown,
        f"unknown {name} parameter(s): {', '.join(unknown)}; known: {', '.join(sorted(known))}",
    )
    return cls(**check_types(cls, values, name))


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)
